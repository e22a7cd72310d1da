"""The bad-input corpus (tests/corpus/, made by tests/corpus/make_corpus.py): every file, fed to the CLI
command that reads its kind, exits 2 with exactly one stderr line naming the file, and leaves no
output behind (docs/ARCHITECTURE.md: the CLI's exit codes)."""

from pathlib import Path

import pytest

from lungdeform.cli.main import main
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.io.modelfile import save_model
from lungdeform.model.lung import Model, build_lung
from tests.io.dicom_support import write_ct_series

CORPUS = Path(__file__).resolve().parents[1] / "corpus"
FILES = sorted(p for p in CORPUS.glob("*/*") if p.is_file())


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    s = icosphere(2, 1.0)
    lung = build_lung(Surface(s.vertices * [45.0, 70.0, 110.0] + [90.0, 20.0, -150.0], s.faces, "left"), "left")
    return save_model(tmp_path_factory.mktemp("model") / "m.npz", Model({"left": lung}))


@pytest.fixture(scope="module")
def reference_ct(tmp_path_factory):
    """The CT the corpus RTSTRUCTs' GTV lies on (tests/corpus/make_corpus.py): 2 mm axial slices,
    z = -169 … -131 mm, around the model's lung at (90, 20, -150), with the default UIDs."""
    return write_ct_series(tmp_path_factory.mktemp("ct") / "ct", shape=(20, 16, 16), origin=(75.0, 5.0, -169.0))


def _command(kind: str, bad: Path, out: Path, model: Path, ct: Path) -> list[str]:
    return {
        "mesh": ["build", str(bad), "--side", "left", "--out", str(out / "m.npz")],
        "image": ["build", str(bad), "--side", "left", "--out", str(out / "m.npz")],
        "model": ["export", str(bad), "--format", "glb", "--out", str(out / "m.glb")],
        "curve": ["export", str(model), "--format", "glb", "--curve", str(bad), "--out", str(out / "m.glb")],
        "trace": ["breathe", "--fit", str(bad), "--out", str(out)],
        "points": ["track", str(model), "--points", str(bad), "--volume-ml", "100", "--out", str(out)],
        "manifest": ["cohort", str(bad), "--out", str(out)],
        "rtstruct": ["track", str(model), "--rtstruct", str(bad), "--structure", "GTV", "--volume-ml", "100",
                     "--out", str(out), "--out-rtstruct", str(out / "moved.dcm"), "--reference-ct", str(ct)],
    }[kind]


def test_the_corpus_is_there():
    # why: a glob that finds nothing would pass the test below vacuously
    assert len(FILES) >= 30 and {p.parent.name for p in FILES} >= {"mesh", "image", "model", "curve", "trace",
                                                                    "points", "manifest", "rtstruct"}


@pytest.mark.parametrize("bad", FILES, ids=[f"{p.parent.name}/{p.name}" for p in FILES])
def test_bad_file_exits_2_with_one_line(bad, tmp_path, model_file, reference_ct, capsys):
    # why: each file is broken on purpose (its name says how); the reader must refuse it with the
    # package's error, which the CLI prints as one line naming the file, before writing anything.
    out = tmp_path / "out"
    code = main(_command(bad.parent.name, bad, out, model_file, reference_ct))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert bad.name in err[0], err
    assert not out.exists() or not any(out.iterdir()), list(out.rglob("*"))
