"""The ``--dask`` address (docs/distributed.md): ``local[:N]``, a scheduler's
``tcp://HOST:PORT``, or $DASK_SCHEDULER_ADDRESS; parsed by the command line
before anything imports Dask, and the peer timeout a shared cluster may ask for."""
from __future__ import annotations

import dataclasses
import os

from ...base.errors import BakeError

#: The environment variable ``--dask`` without an address reads (Dask's own name).
ENV_ADDRESS = "DASK_SCHEDULER_ADDRESS"
#: local:N: at most this many worker processes.
MAX_LOCAL_WORKERS = 256
#: Seconds a new connection to a scheduler or worker already reached may take
#: to open. A scheduler killed while a result was being fetched made that
#: fetch retry the dead address for dask_cluster.CONNECT_TIMEOUT (CI, 2026-11-24).
PEER_CONNECT_TIMEOUT = 3.0
#: Environment variable that replaces PEER_CONNECT_TIMEOUT for a scheduler
#: address (a shared cluster whose TLS handshakes take longer under load), in
#: seconds within PEER_TIMEOUT_RANGE.
ENV_PEER_TIMEOUT = "PRTT_DASK_PEER_TIMEOUT"
PEER_TIMEOUT_RANGE = (0.5, 300.0)


@dataclasses.dataclass(frozen=True)
class DaskSpec:
    """A parsed ``--dask`` value: ``local`` with ``workers`` processes, or a
    scheduler ``address`` (tcp://host:port, tls://...)."""

    kind: str                  # "local" | "address"
    workers: int = 0
    address: str = ""
    peer_timeout: float = PEER_CONNECT_TIMEOUT   # seconds (PEER_CONNECT_TIMEOUT, $PRTT_DASK_PEER_TIMEOUT)

    def describe(self) -> str:
        return f"a local cluster of {self.workers} worker processes" if self.kind == "local" \
            else f"the Dask scheduler at {self.address}"


def parse_spec(spec: str, environ=None) -> DaskSpec:
    """``local``, ``local:N``, ``tcp://HOST:PORT`` (any ``scheme://``), or
    ``env`` / empty: the address in $DASK_SCHEDULER_ADDRESS. BakeError naming
    the value otherwise."""
    environ = os.environ if environ is None else environ
    s = (spec or "").strip()
    if s in ("", "env"):
        s = (environ.get(ENV_ADDRESS) or "").strip()
        if not s:
            raise BakeError(f"--dask without an address reads ${ENV_ADDRESS}, which is not set; "
                            f"give local[:N] or tcp://HOST:PORT")
        if s.startswith("local"):
            raise BakeError(f"${ENV_ADDRESS} must be a scheduler address (tcp://HOST:PORT), got {s!r}")
    if s == "local":
        return DaskSpec("local", max(1, os.cpu_count() or 1))
    if s.startswith("local:"):
        n = s[len("local:"):]
        if not n.isdigit() or not 1 <= int(n) <= MAX_LOCAL_WORKERS:
            raise BakeError(f"--dask local:N needs N = 1..{MAX_LOCAL_WORKERS} worker processes, got {spec!r}")
        return DaskSpec("local", int(n))
    scheme, sep, rest = s.partition("://")
    if not sep or not scheme.isalnum() or not rest or any(c.isspace() for c in rest):
        raise BakeError(f"--dask must be local, local:N or a scheduler address like tcp://HOST:PORT, got {spec!r}")
    return DaskSpec("address", address=s, peer_timeout=peer_timeout(environ))


def peer_timeout(environ) -> float:
    """PEER_CONNECT_TIMEOUT, or $PRTT_DASK_PEER_TIMEOUT (seconds, within
    PEER_TIMEOUT_RANGE; BakeError naming the value otherwise)."""
    raw = (environ.get(ENV_PEER_TIMEOUT) or "").strip()
    if not raw:
        return PEER_CONNECT_TIMEOUT
    lo, hi = PEER_TIMEOUT_RANGE
    try:
        v = float(raw)
    except ValueError:
        v = float("nan")
    if not lo <= v <= hi:                       # also refuses nan and inf
        raise BakeError(f"${ENV_PEER_TIMEOUT} must be seconds from {lo:g} to {hi:g}, got {raw!r}")
    return v
