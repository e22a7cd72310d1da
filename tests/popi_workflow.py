"""The README workflow's first steps on the POPI phase-00 CT (real data), shared by the data tests
that need a real CT, its model and a smaller DICOM copy of it: tests/cli/test_warp.py,
tests/cli/test_fit.py and tests/test_docs_radiotherapy.py."""

from __future__ import annotations

import tarfile
from pathlib import Path

from lungdeform.cli.main import main
from lungdeform.io.dicom import series as DS
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from tests.conftest import require_path


def extract_popi(data_dir, folder: Path) -> Path:
    """The POPI phase-00 DICOM series extracted into ``folder``: its path (``folder/popi00``)."""
    archive = require_path(data_dir, "popi-ct-phase00", "popi_phase00_dicom_141slices.tar.gz")
    with tarfile.open(archive) as tar:
        tar.extractall(folder, filter="data")
    return Path(folder) / "popi00"


def popi_model(popi: Path, tmp_path: Path, target_vertices: int) -> Path:
    """``segment --downsample 4`` then ``build`` on the POPI CT: the model file (tmp_path/model.npz)."""
    assert main(["segment", str(popi), "--out", str(tmp_path / "seg"), "--downsample", "4"]) == 0
    model = tmp_path / "model.npz"
    assert main(["build", str(tmp_path / "seg" / "left_lung.nii.gz"), str(tmp_path / "seg" / "right_lung.nii.gz"),
                 "--target-vertices", str(target_vertices), "--out", str(model)]) == 0
    return model


def downsampled_series(popi: Path, out: Path, step_zyx: tuple[int, int, int]):
    """The POPI CT every ``step_zyx`` voxels (z, y, x) written to ``out`` as a DICOM CT series that
    keeps POPI's study and Frame of Reference: its study header (pydicom Dataset)."""
    ct, head = read_image(popi), DS.study_header(popi)
    sz, sy, sx = step_zyx
    DS.write_ct_series(out, Image(ct.array[::sz, ::sy, ::sx], ct.spacing * [sx, sy, sz], ct.origin, ct.direction),
                       head, description=head.SeriesDescription)
    return head
