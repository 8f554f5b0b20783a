"""Coverage-guided fuzzing of every reader of outside data (dev-only: not in
the extension zip). ``./prtt.sh fuzz [reader ...] [--runs N | --seconds S]``;
docs/fuzzing.md. targets.py holds one target per reader, seeds.py the seed
corpora (real files the project writes), harness.py runs one target under
atheris (libFuzzer) in its own process, __main__.py runs them and reports."""
