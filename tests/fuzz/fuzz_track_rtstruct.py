"""Fuzz harness: track_rtstruct, the RTSTRUCT + reference CT workflow of `track --out-rtstruct` (tests/fuzz/common.py says what is checked). Run: python tests/fuzz/fuzz_track_rtstruct.py --runs N --seconds S"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script: the repository root
from tests.fuzz import common  # noqa: E402

READER = "track_rtstruct"


def TestOneInput(data: bytes) -> None:  # noqa: N802 - atheris's name
    common.test_one_input(READER, data)


if __name__ == "__main__":
    common.main(READER, TestOneInput)
