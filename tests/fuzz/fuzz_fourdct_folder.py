"""Fuzz harness: fourdct_folder (tests/fuzz/common.py says what is checked). Run: python tests/fuzz/fuzz_fourdct_folder.py --runs N --seconds S"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script: the repository root
from tests.fuzz import common  # noqa: E402

READER = "fourdct_folder"


def TestOneInput(data: bytes) -> None:  # noqa: N802 - atheris's name
    common.test_one_input(READER, data)


if __name__ == "__main__":
    common.main(READER, TestOneInput)
