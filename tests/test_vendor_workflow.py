"""The radiotherapy workflow (docs/RADIOTHERAPY.md) on DICOM that no lungdeform code wrote, as exports come.

Input (tests/vendor_dicom.py, plain pydicom): the chest phantom of tests/segment/test_lungs.py as a
vendor-like CT export — random file names without a suffix in random order, InstanceNumber unrelated
to position, Rescale slope 0.5 / intercept −1100 over 12-bit unsigned pixels, private tags, a Latin-1
patient name, every third file implicit VR, a localizer and a second (thicker) reconstruction in the
same folder — and beside it what a planning system exports with it (issue 36): a structure set of 30
ROIs (names in Chinese, Greek, Arabic, with combining characters; empty ROIs, POINT ROIs; the GTV
``GTV_β肿瘤`` with a mask-to-contour tool's tips of 1 and 2 points, a repeated-point and a collinear
contour), an RTPLAN, an RTDOSE grid, a rigid REG, a KO, a README and a ``Thumbs.db``; the same export
as a CD (a DICOMDIR over PT*/ST*/SE* folders). Then: segment (the CD) → build → ``warp --phases 10``
(DICOM) → the ten phases copied into one folder with the plan's objects beside them → ``fit`` on that
folder → ``track --scan K --out-rtstruct`` on each phase (chosen with ``--series-description``) with the
planning system's structure set → ``dvf --out-reg``; dciodvfy on every RTSTRUCT, CT phase and REG written.
Each command names what it ignored, in one line.
"""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from lungdeform.cli.main import main
from lungdeform.io.dicom.folder import SeriesChoice
from lungdeform.io.dicom.rtstruct import read_ct_series, read_rtstruct
from lungdeform.io.image import read_image
from tests.io.dicom_support import dciodvfy
from tests.segment.test_lungs import phantom
from tests.vendor_dicom import (
    EXTRAS,
    FRAME_UID,
    GTV_NAME,
    PATIENT,
    write_dicomdir_export,
    write_export_extras,
    write_vendor_ct,
)

GTV, RADIUS = np.array([-45.0, -8.0, 10.0]), 10.0  # mm LPS: inside the phantom's right lung
MAIN = "Thorax 3.0 Br40 Planning"  # the main series' description (the other is 'Thorax 6.0 Br40')

pytestmark = pytest.mark.slow


def _curve(path):
    t = np.linspace(0, 8, 161)  # two 4 s breaths of 300 mL (both lungs) from end-exhale
    path.write_text("t_s,volume_ml\n" + "".join(f"{a:.3f},{150 * (1 - np.cos(np.pi * a / 2)):.3f}\n" for a in t))
    return path


def _flat_4dct(d, extras) -> None:
    """The ten phase series of ``d/4dct`` in one folder ``d/4d`` (as a 4-D CT export holds them), with
    the plan's structure set, plan, dose, README and Thumbs.db beside them."""
    flat = d / "4d"
    flat.mkdir()
    for phase in sorted((d / "4dct").iterdir()):
        for f in phase.iterdir():
            shutil.copy(f, flat / f"{phase.name}_{f.name}")
    for name in ("RS_plan.dcm", "RP_plan.dcm", "RD_plan.dcm", "README.txt", "Thumbs.db"):
        shutil.copy(extras[name], flat / name)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The workflow up to the fit, once for the module: its folder, what each step gave and printed."""
    rng = np.random.default_rng(20261127)
    d = tmp_path_factory.mktemp("vendor")
    image, truth = phantom(rng, gap_mm=10.0)
    ct = write_vendor_ct(d / "export", image, rng)
    extras = write_export_extras(d / "export", image, ct, rng, gtv=(GTV, RADIUS))
    write_dicomdir_export([f for f in (d / "export").iterdir() if f.name not in ("README.txt", "Thumbs.db")], d / "cd")
    said = {}
    steps = {"segment": ["segment", str(d / "cd"), "--series-description", MAIN, "--out", str(d / "seg")],
             "build": ["build", str(d / "seg" / "left_lung.nii.gz"), str(d / "seg" / "right_lung.nii.gz"),
                       "--target-vertices", "600", "--out", str(d / "model.npz")],
             "warp": ["warp", str(d / "export"), str(d / "model.npz"), "--series-description", MAIN, "--curve",
                      str(_curve(d / "c.csv")), "--phases", "10", "--node-mm", "12", "--out", str(d / "4dct")],
             "fit": ["fit", str(d / "4d"), "--side", "right", "--out", str(d / "fit"), "--no-baselines",
                     "--no-stiffness", "--direction-degree", "0", "--evaluations", "10"]}
    for name, argv in steps.items():
        if name == "fit":
            _flat_4dct(d, extras)
        said[name] = _run(argv)
    metrics = json.loads((d / "fit" / "metrics.json").read_text())
    # scan K of the fit is the phase of this label: "…4d [30%]" → the series "… phase 30%" in d/4d
    percents = [int(float(p.rsplit("[", 1)[1].rstrip("%]"))) for p in metrics["inputs"]]
    return {"dir": d, "image": image, "truth": truth, "ct": ct, "percents": percents, "said": said,
            "phases": [d / "4dct" / f"phase{p:02d}" for p in percents]}


def _run(argv) -> str:
    """``lungdeform ARGV`` (exit 0 asserted); what it printed on stdout."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    assert code == 0, err.getvalue()
    return out.getvalue()


def test_the_vendor_export_reads_as_the_volume_it_holds(run):
    # truth: the phantom's HU (slope and intercept applied, slices ordered by position whatever the
    # file order, names and InstanceNumbers, the localizer, the thicker series and the plan's objects
    # left out), and the segmented right lung against the phantom's analytic one; the export itself
    # is legal DICOM
    img = read_image(run["dir"] / "export", series=SeriesChoice(description=MAIN))
    assert img.array.shape == run["image"].array.shape
    assert np.array_equal(img.array.astype(float), np.asarray(run["image"].array, float))
    assert np.allclose(img.origin, run["image"].origin) and np.allclose(img.spacing, run["image"].spacing)
    seg = read_image(run["dir"] / "seg" / "right_lung.nii.gz").array > 0
    truth = run["truth"]["right"]
    assert 2 * (seg & truth).sum() / (seg.sum() + truth.sum()) > 0.95
    for f in (run["ct"]["files"][0], run["ct"]["files"][1], run["dir"] / "export" / "RS_plan.dcm"):  # explicit, implicit VR
        assert dciodvfy(f)[0] == []


def test_each_command_names_what_it_ignored(run):
    # segment followed the CD's DICOMDIR; segment, warp and fit each said, in one line, every object
    # they left out, by name and kind: nothing dropped without a word, nothing read that is no CT
    said = run["said"]
    seg = [ln for ln in said["segment"].splitlines() if ln.startswith("note:")]
    assert len(seg) == 1 and "followed its DICOMDIR (" in seg[0]
    for what in ("(RTSTRUCT)", "(RTPLAN)", "(RTDOSE grid)", "(REG)", "(KO)", "README.TXT (no DICOM)",
                 "'Thorax 6.0 Br40' (25 CT image(s), another series)", "'Topogram 0.6 T20f' (1 CT image(s), a localizer)"):
        assert what in seg[0], what
    warp = [ln for ln in said["warp"].splitlines() if ln.startswith("note: IMAGE")]
    assert len(warp) == 1
    for name, what in EXTRAS.items():
        assert f"{name} ({what})" in warp[0], name
    fit = [ln for ln in said["fit"].splitlines() if "ignored" in ln]
    assert len(fit) == 1 and all(f"{n} ({EXTRAS[n]})" in fit[0] for n in ("RS_plan.dcm", "RP_plan.dcm", "RD_plan.dcm",
                                                                          "README.txt", "Thumbs.db"))
    assert "4-D CT of 10 phases" in said["fit"]


def test_track_on_every_phase_with_the_planning_systems_structure_set(run, capsys):
    # every fitted scan K is the phase series it was read from, chosen in the one folder of ten phases
    # by its description: `track --scan K --out-rtstruct --reference-ct 4d --series-description
    # "phase P%"` is accepted and writes the GTV (its tips skipped, each said) in the vendor's Frame of
    # Reference on that phase's slices, under its own name. Truth: at scan 0 (the 50 % phase,
    # end-exhale: the rest, the source CT; 0 % is end-inhale, as 4-D CT numbers phases) the GTV is
    # where the planner drew it (each contour a circle of the sphere's radius at its slice, within
    # 0.5 mm); the largest phase moves it; every contour references a slice of its phase; dciodvfy:
    # 0 errors on every structure set written
    d = run["dir"]
    centroids = []
    for k, (percent, phase) in enumerate(zip(run["percents"], run["phases"])):
        rs = d / f"gtv_scan{k}.dcm"
        assert main(["track", str(d / "fit" / "model.npz"), "--rtstruct", str(d / "export" / "RS_plan.dcm"),
                     "--structure", GTV_NAME, "--scan", str(k), "--out", str(d / f"track{k}"), "--out-rtstruct", str(rs),
                     "--reference-ct", str(d / "4d"), "--series-description", f"phase {percent}%"]) == 0, \
            capsys.readouterr().err
        said = capsys.readouterr().err  # what was done to the input: on stderr, once every check passed
        skipped = [ln for ln in said.splitlines() if "encloses no area: skipped" in ln]
        assert len(skipped) == 4 and all(f"structure '{GTV_NAME}': contour" in ln for ln in skipped)
        moved = read_rtstruct(rs)
        assert list(moved) == [f"{GTV_NAME}@scan{k}", f"ITV_{GTV_NAME}"]
        gtv = moved[f"{GTV_NAME}@scan{k}"]
        assert gtv.frame_uid == FRAME_UID and gtv.patient_id == PATIENT["PatientID"]
        assert gtv.image_uids <= set(read_ct_series(phase).sop_uids)
        centroids.append(np.concatenate(gtv.contours).mean(axis=0))
        if k == 0:
            assert phase.name == "phase50"
            for c in gtv.contours:
                r = np.sqrt(max(RADIUS ** 2 - (c[0, 2] - GTV[2]) ** 2, 0.0))
                assert np.abs(np.linalg.norm(c[:, :2] - GTV[:2], axis=1) - r).max() < 0.5
        assert dciodvfy(rs)[0] == [], rs
    assert np.linalg.norm(centroids[-1] - centroids[0]) > 1.0  # the largest volume moves the GTV
    rs = d / f"gtv_scan{len(run['phases']) - 1}.dcm"
    assert pydicom.dcmread(rs).SpecificCharacterSet == "ISO_IR 192"  # Müller and GTV_β肿瘤, as UTF-8
    for phase in run["phases"]:
        assert dciodvfy(min(phase.iterdir()))[0] == [], phase
    # the moved GTV keeps the planner's RT ROI Interpreted Type; the ITV's is empty (Type 2), since
    # DICOM has no defined term for an ITV: dciodvfy then warns of no undefined interpreted type
    written = read_rtstruct(rs)
    assert written[f"{GTV_NAME}@scan{len(run['phases']) - 1}"].kind == "GTV" and written[f"ITV_{GTV_NAME}"].kind == ""
    assert not [w for w in dciodvfy(rs)[1] if "Interpreted" in w]


def test_reg_from_the_rest_phase_to_the_largest(run):
    # dvf --out-reg with the rest phase fixed and the largest phase moving: both keep the vendor's
    # patient and frame; the raw VectorGridData equals the .mha field sampled on the REG's grid (at
    # most 3 mm: 2 mm in-plane coarsened, 3 mm slices kept); dciodvfy: 0 errors
    from lungdeform.playback.displacement_field import Grid
    from lungdeform.playback.field_grid import coarse_grid, coarsened
    d = run["dir"]
    k = len(run["phases"]) - 1
    assert main(["dvf", str(d / "fit" / "model.npz"), "--reference", str(d / "4d"), "--series",
                 str(read_ct_series(run["phases"][0]).header.SeriesInstanceUID), "--scan", str(k),
                 "--node-mm", "12", "--out", str(d / "dvf.mha"), "--out-reg", str(d / "reg.dcm"),
                 "--moving", str(run["phases"][k])]) == 0
    reg = pydicom.dcmread(d / "reg.dcm")
    assert reg.FrameOfReferenceUID == FRAME_UID and reg.PatientID == PATIENT["PatientID"]
    g = reg.DeformableRegistrationSequence[-1].DeformableRegistrationGridSequence[0]
    nx, ny, nz = (int(n) for n in g.GridDimensions)
    u = np.frombuffer(g.VectorGridData, "<f4").reshape(nz, ny, nx, 3)
    grid = Grid.of(read_image(run["phases"][0]))
    full = sitk.GetArrayFromImage(sitk.ReadImage(str(d / "dvf.mha")))
    assert max(float(x) for x in g.GridResolution) <= 3.0 and (nz, ny, nx) == coarse_grid(grid, 3.0).shape
    assert np.abs(u - coarsened(full, grid, coarse_grid(grid, 3.0))).max() < 0.01
    assert np.abs(u).max() > 1.0
    assert dciodvfy(d / "reg.dcm")[0] == []


def test_an_rtstruct_written_by_rt_utils(run, tmp_path, capsys):
    # another library's RTSTRUCT (rt-utils: a mask turned into polygons by OpenCV, on the main series
    # copied apart, as rt-utils reads every file of its folder): read, tracked on the rest phase and
    # written; truth: the polygons trace the 10 mm ball's boundary pixels (2 mm), so every written
    # point lies 7 to 11 mm from its centre
    rt_utils = pytest.importorskip("rt_utils", reason="rt-utils not installed (pip install rt-utils; optional)")
    clean = tmp_path / "main_series"
    clean.mkdir()
    for f in run["ct"]["files"]:
        shutil.copy(f, clean / (f.rsplit("/", 1)[-1] + ".dcm"))
    img = run["image"]
    k, j, i = np.meshgrid(*(np.arange(n) for n in img.array.shape), indexing="ij")
    p = np.stack([i, j, k], -1) * img.spacing + img.origin
    ball = np.linalg.norm(p - GTV, axis=-1) <= RADIUS  # (z, y, x) → rt-utils' (rows, columns, slices)
    with warnings.catch_warnings():  # rt-utils 1.2.7 uses pydicom attributes pydicom 3 deprecates
        warnings.simplefilter("ignore", DeprecationWarning)
        rt = rt_utils.RTStructBuilder.create_new(dicom_series_path=str(clean))
        rt.add_roi(mask=np.transpose(ball, (1, 2, 0)), name="GTV")
        rt.save(str(tmp_path / "rtu.dcm"))
    capsys.readouterr()
    d = run["dir"]
    assert pydicom.dcmread(tmp_path / "rtu.dcm").ReferencedFrameOfReferenceSequence[0].FrameOfReferenceUID == FRAME_UID
    assert main(["track", str(d / "fit" / "model.npz"), "--rtstruct", str(tmp_path / "rtu.dcm"), "--structure", "GTV",
                 "--scan", "0", "--out", str(tmp_path / "t"), "--out-rtstruct", str(tmp_path / "out.dcm"),
                 "--reference-ct", str(run["phases"][0])]) == 0, capsys.readouterr().err
    pts = np.concatenate(read_rtstruct(tmp_path / "out.dcm")["GTV@scan0"].contours)
    r = np.linalg.norm(pts - GTV, axis=1)
    assert r.min() > 7.0 and r.max() < 11.0
    assert dciodvfy(tmp_path / "out.dcm")[0] == []
