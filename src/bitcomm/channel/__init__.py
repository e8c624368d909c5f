"""The bit channel (SPEC section 2): K-bit messages with delay, bit flips, drops and a topology
(who hears whom, `TaskConfig.recipient_matrix`), over a batch of episodes; and the conversions
between bits, message indices and one-hot codes.

May import: `bitcomm.config`, `bitcomm.errors`. Knows nothing of the grid, so any environment can
carry its messages.
"""

from bitcomm.channel.core import Channel, bits_to_index, bits_to_onehot, index_to_bits, index_to_onehot

__all__ = ["Channel", "bits_to_index", "bits_to_onehot", "index_to_bits", "index_to_onehot"]
