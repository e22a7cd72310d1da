"""Trajectories of interior points: placement in a lung, exact per-lung scales, motion summary."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.interior.field import KIND_TEXT
from lungdeform.playback.schedule import lung_shares, plain_cycle
from lungdeform.playback.trajectory import (
    end_exhale_ml,
    extrapolation_note,
    interior_meta,
    lung_scales,
    motion_summary,
    place_points,
    point_trajectories,
    read_points,
    trace_frames,
    volume_frames,
)
from tests.browser.support import two_lungs


def test_points_go_to_the_lung_that_holds_them():
    # the test ellipsoids are centred at x = ±90 mm (left lung at x > 0, LPS)
    m = two_lungs(2)
    pts = np.array([[90.0, 0, 0], [-90.0, 10, -20], [160.0, 0, 0]])  # last: 10 mm outside the left lung
    p = place_points(m, pts)
    assert p.lungs.tolist() == ["left", "right", "left"]
    assert p.inside.tolist() == [True, True, False]
    assert 8.0 < p.distance_mm[2] < 12.0
    forced = place_points(m, np.array([[-25.0, 0, 0]]), "right")  # 5 mm outside the right lung
    assert forced.lungs.tolist() == ["right"] and not forced.inside[0]
    with pytest.raises(InputError, match="outside lung right"):  # a left-lung point forced right
        place_points(m, pts[:1], "right")
    with pytest.raises(InputError, match="pts.csv: 1 point.*more than 30 mm outside every lung.*2 \\("):
        place_points(m, np.array([[90.0, 0, 0], [0.0, 0, 400.0]]), source="pts.csv")
    with pytest.raises(InputError, match="not in the model"):
        place_points(m, pts, "middle")


def test_scales_give_each_lung_its_exact_share():
    # truth: the surface at each lung's scale encloses V_EE + share·ΔV (the export's playback)
    m = two_lungs(2)
    dv = np.array([0.0, 250.0, 500.0, -50.0])
    shares = lung_shares(m)
    for name, s in lung_scales(m, dv).items():
        lung = m.lungs[name]
        for sk, v in zip(s, dv):
            assert lung.surface_at(scale=sk).volume_ml == pytest.approx(lung.volume_ee_ml + shares[name] * v, abs=1e-6)


def test_points_on_the_surface_move_with_it():
    # the interior field is the sliding interpolation of the surface's normal motion, so a point on
    # a vertex follows that vertex's normal motion (to a few % of it: the interpolation is smoothed)
    # and slides along the surface; points at end-exhale (ΔV = 0) do not move
    m = two_lungs(2)
    left = m.lungs["left"]
    idx = np.array([0, 10, 40])
    pts = left.surface.vertices[idx]
    dv = np.array([0.0, 300.0])
    traj = point_trajectories(m, pts, place_points(m, pts), dv)
    s = lung_scales(m, dv)["left"][1]
    assert traj[0] == pytest.approx(pts, abs=1e-9)
    assert traj[1] == pytest.approx(left.points_at(pts, scale=s), abs=1e-9)  # the lung's interior field
    n = left.surface.vertex_normals[idx]
    normal = np.einsum("ij,ij->i", left.positions_at(s)[idx] - pts, n)
    assert np.einsum("ij,ij->i", traj[1] - pts, n) == pytest.approx(normal, abs=0.1 * np.abs(normal).max())
    summary = motion_summary(traj, pts)
    assert summary["max_excursion_mm"] == pytest.approx(np.linalg.norm(traj[1] - traj[0], axis=1).tolist())


def test_read_points_csv_and_elastix(tmp_path):
    from lungdeform.errors import ReadError
    from lungdeform.io.landmarks import write_elastix_points

    (tmp_path / "p.csv").write_text("x_mm,y_mm,z_mm,label\n1,2,3,tumour\n4,5,6,clip\n")
    pts, labels = read_points(tmp_path / "p.csv")
    assert pts.tolist() == [[1, 2, 3], [4, 5, 6]] and labels == ["tumour", "clip"]
    write_elastix_points(tmp_path / "p.txt", pts)
    again, labels = read_points(tmp_path / "p.txt")
    assert again == pytest.approx(pts) and labels == ["point 1", "point 2"]
    (tmp_path / "i.txt").write_text("index\n1\n10 20 30\n")
    with pytest.raises(ReadError, match="'index' point file holds voxel indices"):
        read_points(tmp_path / "i.txt")
    with pytest.raises(ReadError, match="no such points file"):
        read_points(tmp_path / "missing.csv")


def test_markers_csv_with_a_byte_order_mark(tmp_path):
    from lungdeform.playback.trajectory import read_markers_csv

    path = tmp_path / "m.csv"
    path.write_text("x_mm,y_mm,z_mm,label\n90,10,-20,tumour\n-90,0,50\n", encoding="utf-8-sig")
    pts, labels = read_markers_csv(path)
    np.testing.assert_array_equal(pts, [[90, 10, -20], [-90, 0, 50]])
    assert labels == ["tumour", "marker 2"]


def test_volume_frames_are_volumes_above_end_exhale():
    m = two_lungs(2)
    v_ee = end_exhale_ml(m)
    # truth: the model's end-exhale volume is the sum of its lungs' (each lung's own volume at scale 0)
    assert v_ee == pytest.approx(sum(lung.surface_at(scale=0.0).volume_ml for lung in m.lungs.values()))
    frames = volume_frames(m, [v_ee, v_ee + 300.0])
    assert frames.delta_ml == pytest.approx([0.0, 300.0]) and frames.t_s is None
    assert frames.source == f"volumes {v_ee:g}, {v_ee + 300.0:g} mL (end-exhale {v_ee:.0f} mL)"
    with pytest.raises(InputError, match="volumes_ml must be > 0 mL"):
        volume_frames(m, [v_ee, -5.0])


def test_trace_frames_sample_the_trace_at_fps():
    trace = plain_cycle(500.0, period_s=4.0)
    frames = trace_frames(trace, 10.0)
    # 4 s at 10 frames per second: 40 intervals, first and last sample included
    assert frames.t_s == pytest.approx(np.linspace(0.0, 4.0, 41))
    # the cosine breath: 0 at both ends, the tidal volume half-way (t = 2 s is a sample of the trace)
    assert frames.delta_ml[[0, 20, 40]] == pytest.approx([0.0, 500.0, 0.0], abs=1e-9)
    assert frames.source == trace.source
    assert len(trace_frames(trace, 0.01).t_s) == 2  # at least one interval
    with pytest.raises(InputError, match="fps must be > 0"):
        trace_frames(trace, 0.0)


def test_extrapolation_note_outside_the_fitted_range():
    m = two_lungs(2)
    fitted = sum(lung.calibration_ml for lung in m.lungs.values())
    # inside: from end-exhale (1 mL below is rounding) to 1.5 times the volume change fitted for
    assert extrapolation_note(m, [-1.0, 1.5 * fitted]) is None
    assert "outside the model's range" in extrapolation_note(m, [-2.0, 10.0])
    assert f"to {1.5 * fitted + 1:+.0f} mL" in extrapolation_note(m, [0.0, 1.5 * fitted + 1])


def test_interior_meta_names_each_lungs_field():
    m = two_lungs(2)
    meta = interior_meta(m)
    # a built model has no landmark correction: each field is its kind's surface part alone
    assert meta["landmark_correction"] == {"left": False, "right": False}
    assert meta["interior_field"] == {name: KIND_TEXT[lung.interior_kind][0] for name, lung in m.lungs.items()}


def test_markers_csv_names_invalid_rows_by_file_line(tmp_path):
    from lungdeform.errors import ReadError
    from lungdeform.playback.trajectory import read_markers_csv

    # lines 3 (NaN), 5 (text) and 7 (inf) are bad; line 4 is blank and still counted as a file line
    path = tmp_path / "m.csv"
    path.write_text("x_mm,y_mm,z_mm\n1,2,3\nnan,0,0\n\nabc,0,0\n4,5,6\n0,inf,0\n")
    with pytest.raises(ReadError, match=r"m.csv: 3 row\(s\) without finite numbers .* at line\(s\) 3, 5, 7 \("):
        read_markers_csv(path)
    skipped = []
    pts, labels = read_markers_csv(path, skip_invalid=True, skipped=skipped)
    assert pts.tolist() == [[1, 2, 3], [4, 5, 6]] and skipped == [3, 5, 7]
    assert labels == ["marker 1", "marker 4"]  # numbered by data row, as before
    # more than five bad rows: the first five and how many
    path.write_text("x_mm,y_mm,z_mm\n" + "nan,0,0\n" * 7 + "1,2,3\n")
    with pytest.raises(ReadError, match=r"7 row\(s\) .* at line\(s\) 2, 3, 4, 5, 6, …"):
        read_markers_csv(path)
    path.write_text("x_mm,y_mm,z_mm\nnan,0,0\n")  # nothing valid left
    with pytest.raises(ReadError, match="no marker rows with finite"):
        read_markers_csv(path, skip_invalid=True)


def test_one_lung_range_is_the_both_lung_breath_it_was_built_for():
    # a lone left lung built for 500 mL (both lungs) is calibrated at its 46.4 %, 232 mL: a 500 mL breath
    # is inside its range, 1.5 × 500 mL is the edge; the lung plays 46.4 % of ΔV (measured on the mesh)
    from lungdeform.model.lung import build_model
    from tests.conftest import ellipsoid_lung

    m = build_model({"left": ellipsoid_lung("left", 2)}, tidal_ml=500.0, default="paper")
    assert extrapolation_note(m, [0.0, 500.0]) is None
    assert extrapolation_note(m, [0.0, 750.0]) is None
    assert "(0 to 500 mL)" in extrapolation_note(m, [0.0, 751.0])
    lung = m.lungs["left"]
    (s,) = lung_scales(m, [500.0])["left"]
    assert lung.surface_at(scale=s).volume_ml == pytest.approx(lung.volume_ee_ml + 0.464 * 500.0, abs=1e-6)


def test_points_file_that_is_a_folder_or_empty(tmp_path):
    # a folder is named as one (it used to be "no such points file" though the path exists); an empty
    # or blank file is named as empty (it used to say "markers need a header"), and a CSV read as
    # points to track speaks of points, as the same reader does of markers for export --markers
    from lungdeform.errors import ReadError
    from lungdeform.playback.trajectory import read_markers_csv

    (tmp_path / "d").mkdir()
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "blank.csv").write_text("\n  \n")
    (tmp_path / "nohead.csv").write_text("a,b\n1,2\n")
    expected = {
        "d": "is a folder, not a points file (give a CSV x_mm,y_mm,z_mm[,label] or an elastix 'point' file)",
        "empty.csv": "the points file is empty (expected a CSV with header x_mm,y_mm,z_mm[,label] or an "
                     "elastix 'point' file)",
        "blank.csv": "the points file is empty (expected a CSV with header x_mm,y_mm,z_mm[,label] or an "
                     "elastix 'point' file)",
        "nohead.csv": "points need a header with x_mm,y_mm,z_mm[,label]",
    }
    for name, message in expected.items():
        with pytest.raises(ReadError) as info:
            read_points(tmp_path / name)
        assert str(info.value) == f"{tmp_path / name}: {message}"
    with pytest.raises(ReadError) as info:
        read_markers_csv(tmp_path / "empty.csv")
    assert str(info.value) == f"{tmp_path / 'empty.csv'}: the markers file is empty (expected a CSV with header " \
                              "x_mm,y_mm,z_mm[,label])"
    with pytest.raises(ReadError) as info:
        read_markers_csv(tmp_path / "d")
    assert str(info.value) == f"{tmp_path / 'd'}: is a folder, not a markers file (give a CSV x_mm,y_mm,z_mm[,label])"
    (tmp_path / "p.csv").write_text("x_mm,y_mm,z_mm\n1,2,3\n")
    assert read_points(tmp_path / "p.csv")[1] == ["point 1"]  # numbered as the elastix reader numbers them


def test_an_end_inhale_model_breathes_out_below_its_scan():
    # why: an end-inhale scan lies S = 500 mL above end-exhale; every state is a volume above
    # end-exhale and each lung moves from its scan by its share of ΔV − S. Truths: at ΔV = S the
    # points stay where drawn (the scan); the end-inhale model at ΔV is the same lungs read as an
    # end-exhale scan at ΔV − S (one field, its origin moved); at ΔV = 0 each lung's surface encloses
    # exactly its scan volume less its share of S (the volume measured from the moved vertices)
    from lungdeform.geometry.mesh import signed_volume
    from lungdeform.model.lung import Model
    from lungdeform.model.scan_state import ScanState
    from lungdeform.playback.trajectory import scan_ml, volumes_in_words
    ee = two_lungs(2)
    inhaled = Model(ee.lungs, ee.provenance, ScanState("end-inhale", 500.0))
    pts = np.array([[90.0, 0, 0], [-90.0, 10, -20]])
    place = place_points(inhaled, pts)
    moved = point_trajectories(inhaled, pts, place, [500.0, 250.0, 0.0])
    assert moved[0] == pytest.approx(pts, abs=1e-12)
    assert moved == pytest.approx(point_trajectories(ee, pts, place, [0.0, -250.0, -500.0]), abs=1e-12)
    assert np.all(np.linalg.norm(moved[2] - pts, axis=1) > 1.0)
    shares = lung_shares(inhaled)
    for name, s in lung_scales(inhaled, [0.0]).items():
        lung = inhaled.lungs[name]
        v = signed_volume(lung.positions_at(s[0]), lung.surface.faces) / 1000
        assert v == pytest.approx(lung.volume_ee_ml - shares[name] * 500.0, rel=1e-9)
    assert end_exhale_ml(inhaled) == pytest.approx(scan_ml(inhaled) - 500.0)
    assert "the scan" in volumes_in_words(inhaled) and "end-inhale" in volumes_in_words(inhaled)
    # an absolute volume keeps its meaning: the scan's own volume is the scan, 500 mL above end-exhale
    frames = volume_frames(inhaled, [scan_ml(inhaled), scan_ml(inhaled) - 500.0])
    assert frames.delta_ml == pytest.approx([500.0, 0.0])
    # within the breath (0 to 500 mL above end-exhale) nothing is extrapolated, also below the scan
    assert extrapolation_note(inhaled, [0.0, 250.0, 500.0]) is None
