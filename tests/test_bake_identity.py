"""The bake writes the same bytes as before its memory was reorganised (#35):
every output file of five small bakes, one per bake mode, against the SHA-256
recorded from the earlier code (tests/bake_identity.py, tests/data/bake_identity.json).

The bytes depend on the CPU (Embree's and numpy's SIMD paths round
differently): the record holds the earlier code's output on each machine it
was run on (``cases``, and ``other_machines``: the code at
``recorded_at_commit`` run there), and today's output must be one of them."""
import json

import bake_identity
import pytest

_DATA = json.load(open(bake_identity.RECORD, encoding="utf-8"))
RECORDED = [_DATA["cases"]] + [m["cases"] for m in _DATA.get("other_machines", [])]


@pytest.mark.parametrize("case", sorted(bake_identity.CASES))
def test_outputs_byte_identical(case, tmp_path):
    got = bake_identity.bake_case(case, str(tmp_path))
    # Which files differ from the nearest record tells a changed input (every
    # file, or one set's) from another CPU's rounding (every traced file).
    nearest = min((sorted(f for f in set(got) | set(m[case]) if got.get(f) != m[case].get(f)) for m in RECORDED),
                  key=len)
    assert any(got == machine[case] for machine in RECORDED), (
        f"{case}: not the bytes the code at {_DATA['recorded_at_commit'][:7]} wrote on any machine recorded "
        f"(this CPU: {_cpu()}; {len(nearest)} of {len(got)} files differ from the nearest record: {nearest[:6]}"
        f"{_members(tmp_path, nearest)}); "
        f"on a new kind of CPU, run tests/bake_identity.py --record with that commit's code there and add it to "
        f"other_machines")


def _members(folder, files) -> str:
    """The SHA-256 prefix of each array of the differing .npz files (which array moved: a flaky
    per-vertex transfer was seen once under a loaded suite, issue 50)."""
    import hashlib

    import numpy as np
    out = []
    for f in files:
        if f.endswith(".npz") and (folder / f).exists():
            with np.load(folder / f) as z:
                out.append(f"{f}: " + ", ".join(f"{n} {hashlib.sha256(z[n].tobytes()).hexdigest()[:8]}"
                                                 for n in z.files))
    return ("; " + "; ".join(out)) if out else ""


def _cpu() -> str:
    """The CPU's name and the SIMD paths the bytes depend on (OpenBLAS's kernels: one EPYC ran
    SkylakeX's, another Haswell's, and their bounces differ)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            name = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "?")
    except OSError:
        name = "?"
    try:
        from threadpoolctl import threadpool_info
        blas = ", ".join(f"{i['internal_api']} {i.get('architecture', '?')}" for i in threadpool_info()
                         if i.get("user_api") == "blas")
    except ImportError:              # threadpoolctl is a dependency; without it the name alone
        blas = ""
    return f"{name}{', ' + blas if blas else ''}"
