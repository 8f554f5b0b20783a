"""One fuzz target under atheris (libFuzzer), in its own process:

    python -m prtt_addon.dev.fuzz.harness TARGET [libFuzzer flags and corpus folders]

The target's reader modules are imported inside ``atheris.instrument_imports``
so that libFuzzer sees their branch coverage; an input a target rejects
(targets.Misbehaved, or any exception a target lets through) is a crash,
written where ``-artifact_prefix`` says.
"""
import importlib
import sys

import atheris


def main(argv: list[str]) -> None:
    name = argv[1]
    with atheris.instrument_imports(include=["prtt_addon"]):
        from prtt_addon.dev.fuzz import targets
        for m in targets.TARGETS[name].modules:
            importlib.import_module(m)
    t = targets.TARGETS[name]
    if t.prepare is not None:
        t.prepare()
    run = t.run
    atheris.Setup([argv[0]] + argv[2:], run)
    atheris.Fuzz()


if __name__ == "__main__":
    main(sys.argv)
