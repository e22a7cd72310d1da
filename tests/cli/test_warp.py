"""``lungdeform warp`` on a small synthetic model and image."""

import numpy as np

from lungdeform.cli.main import main
from lungdeform.io.image import read_image
from tests.cli.test_dvf import files  # noqa: F401  (the shared module fixture)


def test_warp_keeps_labels_and_metadata(files, tmp_path):
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    out = tmp_path / "w.nii.gz"
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--volume-ml", str(ee + 300), "--label",
                 "--out", str(out)]) == 0
    ref, got = read_image(d / "ref.nii.gz"), read_image(out)
    assert got.array.dtype == ref.array.dtype and set(np.unique(got.array)) == {0, 1, 2}
    assert np.allclose(got.origin, ref.origin) and np.allclose(got.spacing, ref.spacing)
    # inhaling: the labelled lungs grow (the boxes stand in for the lungs, so they grow too)
    assert (got.array > 0).sum() > (ref.array > 0).sum()


def test_warp_phases_over_a_curve(files, tmp_path):
    d, _ = files
    curve = tmp_path / "c.csv"
    t = np.linspace(0, 8, 161)
    curve.write_text("t_s,volume_ml\n" + "".join(f"{a:.3f},{250 * (1 - np.cos(np.pi * a / 2)):.3f}\n" for a in t))
    out = tmp_path / "ct.mha"
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--curve", str(curve), "--phases", "2",
                 "--out", str(out)]) == 0
    names = sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".mha")
    assert names == ["ct_phase00.mha", "ct_phase01.mha"]
