"""plastimatch as a second, independent reader of what lungdeform writes (issue 36, item 6).

plastimatch (the ``plastimatch`` package on PyPI ships the command-line tool; requirements.lock pins
it) is a radiotherapy toolkit of its own: its DICOM, RTSTRUCT and vector-field readers and its
warper share no code with lungdeform's. Three checks on a small synthetic CT (a DICOM series of
48 x 48 x 30 voxels of 2 mm around a tumour in the left lung of a two-lung model):

- ``plastimatch warp`` of the CT with lungdeform's inverse field (``dvf --inverse``) equals
  ``lungdeform warp`` of it (|ΔHU| <= 1 after rounding: two linear interpolations of one field);
- ``plastimatch convert`` of lungdeform's tracked RTSTRUCT (every state and the ITV) gives masks
  whose volumes and centroids match lungdeform's own rasterisation of the same structures (centroid
  within half a voxel, volume within 10 % for structures of 1,000 voxels or more: the two rasterise
  the boundary by different rules);
- plastimatch reads every CT phase series of ``warp --phases`` with the geometry of the source and
  lungdeform's voxels.

Without the tool the tests skip, naming it.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from lungdeform.cli.main import main
from lungdeform.io.dicom import series as DS
from lungdeform.io.dicom.rtstruct import read_ct_series, read_rtstruct, structure_mesh, write_rtstruct
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from lungdeform.io.modelfile import save_model
from lungdeform.playback.displacement_field import Grid
from lungdeform.playback.rigid import surface_mask
from tests.browser.support import two_lungs

GTV_CENTRE = np.array([90.0, 0.0, -40.0])  # inside the left lung of two_lungs(2)
SHAPE, SPACING = (30, 48, 48), np.array([2.0, 2.0, 2.0])  # (z, y, x) voxels; (x, y, z) mm
RADIUS = 13.0  # mm: 9.2 mL, about 1,150 voxels of 8 mm³


def plastimatch() -> str:
    """The plastimatch executable (the virtual environment's, else on PATH), or skip naming it."""
    here = Path(sys.executable).parent / "plastimatch"
    found = str(here) if here.is_file() else shutil.which("plastimatch")
    if found is None:
        pytest.skip("plastimatch not installed (pip install plastimatch; requirements.lock pins it): the "
                    "second-reader checks need it")
    return found


def run_plastimatch(*args) -> str:
    done = subprocess.run([plastimatch(), *map(str, args)], capture_output=True, text=True, timeout=300,
                          check=False)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return done.stdout


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """The model, a CT series with texture (HU) around the tumour, a 13 mm spherical GTV drawn on it."""
    plastimatch()
    d = tmp_path_factory.mktemp("plastimatch")
    model = two_lungs(2)
    save_model(d / "model.npz", model)
    rng = np.random.default_rng(36)
    origin = GTV_CENTRE - (np.array(SHAPE[::-1]) - 1) / 2 * SPACING
    k, j, i = np.meshgrid(*(np.arange(n) for n in SHAPE), indexing="ij")
    p = np.stack([i, j, k], -1) * SPACING + origin
    # lung texture: smooth noise about -800 HU, a denser ball (the tumour) and a vessel along y
    from scipy import ndimage

    hu = -800.0 + 120.0 * ndimage.gaussian_filter(rng.normal(size=SHAPE), 2.0) / 0.07
    hu[np.linalg.norm(p - GTV_CENTRE, axis=-1) <= RADIUS] = 30.0
    hu[np.linalg.norm((p - GTV_CENTRE - [8.0, 0, 12.0])[..., [0, 2]], axis=-1) <= 3.0] = 60.0
    image = Image(np.clip(np.rint(hu), -1024, 3000).astype(np.int16), SPACING, origin, np.eye(3))
    DS.write_ct_series(d / "ct", image, DS.study_header(), description="plastimatch test CT")
    s = trimesh.creation.icosphere(4, radius=RADIUS)
    write_rtstruct(d / "gtv.dcm", read_ct_series(d / "ct"), [("GTV", s.vertices + GTV_CENTRE, s.faces, "GTV")])
    v_ee = sum(lung.volume_ee_ml for lung in model.lungs.values())
    return {"dir": d, "model": d / "model.npz", "ct": d / "ct", "gtv": d / "gtv.dcm", "volume": v_ee + 600.0}


def test_plastimatch_warp_with_the_inverse_field_equals_lungdeform_warp(case, tmp_path):
    # truth: one resampling field, two independent warpers (ITK's in lungdeform, plastimatch's own),
    # both trilinear and both pulling the input at y + w(y): the images agree to rounding (≤ 1 HU)
    d = case
    vol = f"{d['volume']:g}"
    assert main(["warp", str(d["ct"]), str(d["model"]), "--volume-ml", vol, "--node-mm", "6",
                 "--out", str(tmp_path / "ld.mha")]) == 0
    assert main(["dvf", str(d["model"]), "--reference", str(d["ct"]), "--volume-ml", vol, "--node-mm", "6",
                 "--inverse", "--out", str(tmp_path / "inv.mha")]) == 0
    ct = read_image(d["ct"])
    run_plastimatch("warp", "--input", d["ct"], "--xf", tmp_path / "inv.mha", "--output-img", tmp_path / "pm.mha",
                    "--interpolation", "linear", "--default-value", int(ct.array.min()))
    ours, theirs = read_image(tmp_path / "ld.mha"), read_image(tmp_path / "pm.mha")
    assert theirs.array.shape == ours.array.shape and np.allclose(theirs.origin, ours.origin, atol=1e-3)
    diff = np.abs(np.rint(ours.array.astype(float)) - np.rint(theirs.array.astype(float)))
    moved = np.abs(ours.array.astype(float) - ct.array.astype(float))
    print(f"plastimatch warp vs lungdeform warp: max |dHU| {diff.max():g}, mean {diff.mean():.4f}, "
          f"voxels changed by the warp {int((moved > 1).sum())} of {moved.size}")
    assert moved.max() > 100  # the field moved the tumour's edge: the comparison is not of two copies
    assert diff.max() <= 1.0


def test_plastimatch_rasterises_the_tracked_rtstruct_as_lungdeform_does(case, tmp_path):
    # truth: lungdeform's own rasterisation (voxel centres inside the closed surface through the
    # written contours, read back) against plastimatch's (its polygon fill of the same contours on the
    # same CT): centroids within half a voxel, volumes within 10 % for structures of ≥ 1,000 voxels
    d = case
    v_ee = d["volume"] - 600.0
    rs = tmp_path / "moved.dcm"
    assert main(["track", str(d["model"]), "--rtstruct", str(d["gtv"]), "--structure", "GTV", "--out",
                 str(tmp_path / "t"), "--volume-ml", f"{v_ee:g}", "--volume-ml", f"{d['volume']:g}",
                 "--out-rtstruct", str(rs), "--reference-ct", str(d["ct"])]) == 0
    run_plastimatch("convert", "--input", rs, "--referenced-ct", d["ct"], "--output-prefix", tmp_path / "masks",
                    "--prefix-format", "nrrd")
    ct = read_image(d["ct"])
    grid = Grid(ct.array.shape, ct.spacing, ct.origin, ct.direction)
    written = read_rtstruct(rs)
    assert len(written) == 3  # two states and the ITV
    for name, structure in written.items():
        theirs = read_image(tmp_path / "masks" / f"{name}.nrrd").array > 0
        v, f = structure_mesh(structure)
        ours = surface_mask(v, f, grid)
        assert theirs.shape == ours.shape
        n_ours, n_theirs = int(ours.sum()), int(theirs.sum())
        c_ours = ct.index_to_world(np.argwhere(ours)[:, ::-1]).mean(axis=0)
        c_theirs = ct.index_to_world(np.argwhere(theirs)[:, ::-1]).mean(axis=0)
        print(f"{name}: lungdeform {n_ours} voxels, plastimatch {n_theirs} ({100 * (n_theirs / n_ours - 1):+.1f} %); "
              f"centroids {np.linalg.norm(c_ours - c_theirs):.3f} mm apart")
        assert n_ours >= 1000
        assert abs(n_theirs / n_ours - 1) <= 0.10
        assert np.linalg.norm(c_ours - c_theirs) <= 0.5 * SPACING.min()


def test_plastimatch_reads_every_phase_series_of_warp_phases(case, tmp_path):
    # truth: each phase folder, read by plastimatch's DICOM reader, has the source CT's grid (size,
    # spacing, origin) and the voxels lungdeform reads from it
    d = case
    curve = tmp_path / "c.csv"
    t = np.linspace(0, 4, 81)
    curve.write_text("t_s,volume_ml\n" + "".join(f"{a:.3f},{300 * (1 - np.cos(np.pi * a / 2)):.3f}\n" for a in t))
    assert main(["warp", str(d["ct"]), str(d["model"]), "--curve", str(curve), "--phases", "4", "--node-mm", "8",
                 "--out", str(tmp_path / "4dct")]) == 0
    src = read_image(d["ct"])
    phases = sorted((tmp_path / "4dct").iterdir())
    assert [p.name for p in phases] == ["phase00", "phase25", "phase50", "phase75"]
    for phase in phases:
        run_plastimatch("convert", "--input", phase, "--output-img", tmp_path / f"{phase.name}.mha")
        theirs, ours = read_image(tmp_path / f"{phase.name}.mha"), read_image(phase)
        assert theirs.array.shape == src.array.shape
        assert np.allclose(theirs.spacing, src.spacing, atol=1e-4) and np.allclose(theirs.origin, src.origin, atol=1e-3)
        assert np.array_equal(theirs.array.astype(float), ours.array.astype(float))
