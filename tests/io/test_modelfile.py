"""``lungdeform.io.modelfile.load_model`` on damaged files: always a ModelFileError naming the file
(the files are the fuzzer's classes, kept in tests/corpus/model/, made by tests/corpus/make_corpus.py)."""

from pathlib import Path

import numpy as np
import pytest

from lungdeform.errors import ModelFileError
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.io.modelfile import load_model, save_model
from lungdeform.model.lung import Model, build_lung

CORPUS = Path(__file__).resolve().parents[1] / "corpus" / "model"


@pytest.mark.parametrize("name, why", [
    ("damaged_deflate.npz", "damaged archive: Error -3"),  # zlib.error before the fix
    ("encrypted_flag.npz", "damaged archive: File 'schema.npy' is encrypted"),  # RuntimeError
    ("zip_version.npz", "damaged archive: zip file version 17.3"),  # NotImplementedError
    ("text_version.npz", "damaged header (schema_version 'three')"),  # ValueError from int()
    ("lone_array.npz", "one NumPy array, not an .npz archive"),  # TypeError: no context manager
    ("empty.npz", "file is empty"),
])
def test_damaged_archives_raise_model_file_error(name, why):
    # why: each file is broken in the way its name says; the message must name the file and the problem
    with pytest.raises(ModelFileError) as info:
        load_model(CORPUS / name)
    assert str(info.value).startswith(str(CORPUS / name)) and why in str(info.value)


def test_lung_arrays_of_text_raise_model_file_error(tmp_path):
    # why: a readable archive whose faces are text passes the shape checks; max() on text raises a
    # TypeError, which must come out as the package's error naming the file
    s = icosphere(1, 1.0)
    lung = build_lung(Surface(s.vertices * [45.0, 70.0, 110.0] + [90.0, 20.0, -150.0], s.faces, "left"), "left")
    path = save_model(tmp_path / "m.npz", Model({"left": lung}))
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["lung/left/faces"] = arrays["lung/left/faces"].astype(str)
    np.savez(tmp_path / "text.npz", **arrays)
    with pytest.raises(ModelFileError, match=r"text\.npz: damaged lung arrays"):
        load_model(tmp_path / "text.npz")
