"""The bake writes the same bytes as before its memory was reorganised (#35):
every output file of five small bakes, one per bake mode, against the SHA-256
recorded from the earlier code (tests/bake_identity.py, tests/data/bake_identity.json)."""
import json

import bake_identity
import pytest

RECORDED = json.load(open(bake_identity.RECORD, encoding="utf-8"))["cases"]


@pytest.mark.parametrize("case", sorted(bake_identity.CASES))
def test_outputs_byte_identical(case, tmp_path):
    assert bake_identity.bake_case(case, str(tmp_path)) == RECORDED[case]
