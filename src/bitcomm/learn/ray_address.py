"""The address of a Ray cluster, as `bitcomm train --address` and `bitcomm.learn.ray_backend` read it: `auto`,
`HOST:PORT` of a head node's GCS (as `ray start --head` prints it) or `ray://HOST:PORT` of a Ray client.
Torch-free, so the command line's parser may import it."""

from __future__ import annotations

import re

ADDRESS = re.compile(r"(ray://)?(?P<host>[A-Za-z0-9._\-\[\]:]*[A-Za-z0-9\]]):(?P<port>\d{1,5})", re.ASCII)
ADDRESS_FORMS = "must be auto, HOST:PORT or ray://HOST:PORT"
"""What an address may be, as an error line says it."""


def host_port(address: str) -> tuple[str, int] | None:
    """`HOST:PORT` or `ray://HOST:PORT` as `(host, port)`, an IPv6 host without its brackets; None for anything
    else (`auto` included) or a port outside 1-65535."""
    match = ADDRESS.fullmatch(address.strip())
    if match is None or not 1 <= int(match["port"]) <= 65535:
        return None
    host = match["host"]
    return (host[1:-1] if host.startswith("[") and host.endswith("]") else host), int(match["port"])
