"""The channel moved to `bitcomm.channel`; this name stays so `bitcomm.envs.channel` imports keep working."""

from bitcomm.channel.core import Channel, bits_to_index, bits_to_onehot, index_to_bits, index_to_onehot

__all__ = ["Channel", "bits_to_index", "bits_to_onehot", "index_to_bits", "index_to_onehot"]
