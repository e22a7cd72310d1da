"""Building a lung model end to end, re-orienting it, and the model file round trip."""

import numpy as np
import pytest

from lungdeform.errors import InputError, ModelFileError
from lungdeform.io.modelfile import SCHEMA_VERSION, load_model, save_model
from lungdeform.model.force import field_basis
from lungdeform.model.graph import spring_graph
from lungdeform.model.lung import Model, build_lung
from lungdeform.model.solve import push
from lungdeform.model.transfer import local_transfer


@pytest.fixture
def model(left_lung):
    return build_lung(left_lung, "left")


def test_volume_linear_over_tidal_range(model):
    # docs/METHOD_NOTES.md §7 (linear in volume): across 500 mL, V(s) matches V_EE + s·ΔV within 1 % (end point exact).
    v0 = model.volume_ee_ml
    for s in np.linspace(0, 500, 11):
        v = model.surface_at(scale=s).volume_ml
        assert abs(v - (v0 + s * model.unit_ml)) <= 0.01 * (v0 + s * model.unit_ml)
    assert model.surface_at(scale=500).volume_ml == pytest.approx(v0 + 500, rel=1e-12)
    # the exact path hits any volume exactly
    assert model.surface_at(v0 + 123.0, exact=True).volume_ml == pytest.approx(v0 + 123.0, rel=1e-12)


def test_force_basis_is_the_solver_response(model, left_lung):
    # The stored responses are what the push loop gives for each field (dense-free reference).
    g = spring_graph(left_lung.vertices, left_lung.edges)
    t = local_transfer(g, model.stiffness)
    fields = field_basis(model.frame.normalized(left_lung.vertices))
    ref = push(t, fields[2], tol=1e-12).kept[: model.n_vertices]
    assert np.abs(model.force_basis[2] - ref).max() <= 1e-6 * np.abs(ref).max()
    # and the force of the model's orientation is the weighted sum
    assert np.allclose(model.force, model.force_weights @ model.force_basis)


def test_stiff_region_moves_less(left_lung):
    # Heterogeneous stiffness: a stiff sphere (tumour) keeps less force, so it moves less.
    from lungdeform.model.stiffness import sphere_override, uniform

    centre = left_lung.vertices[np.argmin(left_lung.vertices[:, 1])]  # anterior surface point
    e = sphere_override(uniform(left_lung.n_vertices), left_lung.vertices, centre, 25.0, 20.0)
    soft = build_lung(left_lung, "left")
    stiff = build_lung(left_lung, "left", stiffness=e)
    inside = np.linalg.norm(left_lung.vertices - centre, axis=1) <= 25.0
    ratio = stiff.force[inside].mean() / soft.force[inside].mean()
    assert ratio < 0.5


def test_orientation_changes_motion_but_keeps_volume(model):
    up = model.oriented("upright")
    assert not np.allclose(up.displacement, model.displacement)
    assert up.surface_at(scale=500).volume_ml == pytest.approx(model.volume_ee_ml + 500, rel=1e-12)
    # supine → supine is the identity
    assert np.allclose(model.oriented("supine").displacement, model.displacement, rtol=1e-12)


def test_solver_choice_does_not_change_the_model(left_lung, model):
    direct = build_lung(left_lung, "left", solver="direct")
    assert np.allclose(direct.displacement, model.displacement, rtol=1e-8, atol=1e-12)


def test_bad_constants_and_stiffness(left_lung):
    with pytest.raises(InputError, match="constants"):
        build_lung(left_lung, "left", constants=[1, 2, 3])
    with pytest.raises(InputError, match="stiffness"):
        build_lung(left_lung, "left", stiffness=np.zeros(left_lung.n_vertices))


def test_model_file_round_trip(tmp_path, model, right_lung):
    m = Model({"left": model, "right": build_lung(right_lung, "right")}, {"source": "test"})
    path = save_model(tmp_path / "lungs", m)
    assert path.name == "lungs.npz" and not list(tmp_path.glob(".*tmp"))
    back = load_model(path)
    assert back.names == ["left", "right"] and back.provenance == {"source": "test"}
    for name in m.names:
        a, b = m.lungs[name], back.lungs[name]
        assert np.array_equal(a.displacement, b.displacement)
        assert np.array_equal(a.surface.faces, b.surface.faces)
        assert b.volume_ee_ml == pytest.approx(a.volume_ee_ml)


def test_schema_1_files_keep_their_thin_plate_interior(tmp_path, model, rng):
    # schema 2 changed only how interior points move: a version-1 file is read, and its interior
    # field is the thin-plate spline of the whole displacement it was made with (truth: that
    # spline, fitted here directly); a version-2 or 3 file uses the sliding field
    from lungdeform.interior.interpolate import displacement_field

    path = save_model(tmp_path / "m.npz", Model({"left": model}))
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    assert int(data["schema_version"]) == SCHEMA_VERSION == 3
    np.savez(tmp_path / "v1.npz", **dict(data, schema_version=np.array(1)))
    old, new = load_model(tmp_path / "v1.npz").lungs["left"], load_model(path).lungs["left"]
    assert (old.interior_kind, new.interior_kind) == ("thin_plate", "sliding")
    v = model.surface.vertices
    q = v.mean(axis=0) + rng.uniform(-5, 5, size=(10, 3))
    ref = displacement_field(v, model.displacement, max_points=4000)(q)
    assert old.interior.displacement(q) == pytest.approx(ref, abs=1e-9)
    assert not np.allclose(new.interior.displacement(q), ref, atol=1e-3)
    # saved again (as schema 3), the old lung keeps its thin-plate field
    again = load_model(save_model(tmp_path / "again.npz", Model({"left": old}))).lungs["left"]
    assert again.interior_kind == "thin_plate"
    assert again.interior.displacement(q) == pytest.approx(ref, abs=1e-9)
    np.savez(tmp_path / "k.npz", **dict(data, **{"lung/left/interior_kind": np.array("spline")}))
    with pytest.raises(ModelFileError, match="interior_kind"):
        load_model(tmp_path / "k.npz")


def test_schema_2_files_keep_their_thin_plate_correction(tmp_path, model, rng):
    # schema 3 changed only the landmark correction: a version-2 file's correction is read as the
    # thin-plate spline it was fitted as (truth: the surface's sliding field plus that spline,
    # built here directly), also when saved again; the same data as schema 3 is the sliding
    # correction, which keeps the surface's normal motion (a different field)
    from dataclasses import replace

    from lungdeform.interior.interpolate import displacement_field
    from lungdeform.interior.sliding import sliding_field

    v, n = model.surface.vertices, model.surface.vertex_normals
    lm = v.mean(axis=0) + rng.uniform(-15, 15, size=(12, 3))
    lung = replace(model, landmarks=lm, landmark_correction=rng.normal(size=(12, 3)), landmark_smoothing=10.0)
    path = save_model(tmp_path / "m.npz", Model({"left": lung}))
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    np.savez(tmp_path / "v2.npz", **dict(data, schema_version=np.array(2)))
    old, new = load_model(tmp_path / "v2.npz").lungs["left"], load_model(path).lungs["left"]
    assert (old.interior_kind, new.interior_kind) == ("sliding_thin_plate", "sliding")
    q = v.mean(axis=0) + rng.uniform(-20, 20, size=(10, 3))
    ref = (sliding_field(v, n, model.displacement)(q)
           + displacement_field(lm, lung.landmark_correction, smoothing=10.0, max_points=12)(q))
    assert old.interior.displacement(q) == pytest.approx(ref, abs=1e-9)
    assert not np.allclose(new.interior.displacement(q), ref, atol=1e-3)
    # schema 3: the same surface part plus the sliding correction with smoothing 10 mm
    from lungdeform.interior.sliding import sliding_correction

    ref3 = sliding_field(v, n, model.displacement)(q) + sliding_correction(v, n, lm, lung.landmark_correction,
                                                                           smoothing=10.0)(q)
    assert new.interior.displacement(q) == pytest.approx(ref3, abs=1e-9)
    again = load_model(save_model(tmp_path / "again.npz", Model({"left": old}))).lungs["left"]
    assert again.interior_kind == "sliding_thin_plate"
    assert again.interior.displacement(q) == pytest.approx(ref, abs=1e-9)
    # a schema-2 lung without landmarks is simply sliding (the two kinds differ only in the correction)
    np.savez(tmp_path / "bare.npz", **dict({k: x for k, x in data.items() if "landmark" not in k},
                                            schema_version=np.array(2)))
    assert load_model(tmp_path / "bare.npz").lungs["left"].interior_kind == "sliding"


def test_interior_vertices_are_saved_and_leave_the_others_out(tmp_path, model, rng):
    # truth: vertices outside interior_vertices (a scan's crop face) carry no data for the interior
    # field, so garbage displacement there changes no interior motion; the mask survives the model
    # file and a re-orientation, and a bad mask is refused naming the key
    from dataclasses import replace

    from lungdeform.errors import ModelFileError

    keep = model.surface.vertices[:, 0] < np.percentile(model.surface.vertices[:, 0], 85)
    lung = replace(model, interior_vertices=keep)
    spoiled = replace(lung, displacement=np.where(keep[:, None], model.displacement, 1e3))
    q = model.surface.vertices.mean(axis=0) + rng.uniform(-5, 5, size=(10, 3))
    assert spoiled.interior.displacement(q) == pytest.approx(lung.interior.displacement(q), abs=1e-9)
    assert not np.allclose(lung.interior.displacement(q), model.interior.displacement(q), atol=1e-6)
    loaded = load_model(save_model(tmp_path / "k.npz", Model({"left": lung}))).lungs["left"]
    assert np.array_equal(loaded.interior_vertices, keep)
    assert loaded.interior.displacement(q) == pytest.approx(lung.interior.displacement(q), abs=1e-12)
    assert np.array_equal(lung.oriented("prone").interior_vertices, keep)
    assert load_model(save_model(tmp_path / "a.npz", Model({"left": model}))).lungs["left"].interior_vertices is None
    with np.load(tmp_path / "k.npz") as z:
        data = {k: z[k] for k in z.files}
    np.savez(tmp_path / "bad.npz", **dict(data, **{"lung/left/interior_vertices": keep[:-1]}))
    with pytest.raises(ModelFileError, match="interior_vertices"):
        load_model(tmp_path / "bad.npz")
    # and the model itself refuses a mask that is not one bool per vertex, or an unknown kind
    from lungdeform.errors import InputError

    with pytest.raises(InputError, match="interior_vertices"):
        replace(model, interior_vertices=np.flatnonzero(keep))
    with pytest.raises(InputError, match="interior_kind"):
        replace(model, interior_kind="spline")


def test_model_file_refuses_wrong_version_and_shapes(tmp_path, model):
    path = save_model(tmp_path / "m.npz", Model({"left": model}))
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    bad = dict(data, schema_version=np.array(SCHEMA_VERSION + 1))
    np.savez(tmp_path / "v.npz", **bad)
    with pytest.raises(ModelFileError, match="version"):
        load_model(tmp_path / "v.npz")
    bad = dict(data)
    bad["lung/left/displacement"] = bad["lung/left/displacement"][:-1]
    np.savez(tmp_path / "s.npz", **bad)
    with pytest.raises(ModelFileError, match="displacement has shape"):
        load_model(tmp_path / "s.npz")
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    (tmp_path / "objects.npy").rename(tmp_path / "objects.npz")  # pickled objects: named as such
    with pytest.raises(ModelFileError, match="objects.npz: not a lungdeform model file \\(it holds Python objects"):
        load_model(tmp_path / "objects.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ModelFileError, match="junk.npz"):
        load_model(tmp_path / "junk.npz")


def test_model_file_keeps_the_landmark_correction(tmp_path, model, rng):
    # the interior correction of a fit with landmarks survives the file (same interior motion),
    # a file with only part of it is refused, and re-orienting drops it (observed in one posture)
    from dataclasses import replace

    lo, hi = model.surface.bounds
    lm = lo + (hi - lo) * rng.uniform(0.3, 0.7, size=(8, 3))
    lung = replace(model, landmarks=lm, landmark_correction=rng.normal(size=(8, 3)), landmark_smoothing=10.0)
    path = save_model(tmp_path / "c.npz", Model({"left": lung}))
    back = load_model(path).lungs["left"]
    assert back.landmark_smoothing == 10.0 and back.interior.corrected
    q = lm + 1.0
    assert back.points_at(q, scale=2.0) == pytest.approx(lung.points_at(q, scale=2.0), abs=1e-9)
    assert not np.allclose(back.points_at(q, scale=2.0), model.points_at(q, scale=2.0))
    assert load_model(save_model(tmp_path / "plain.npz", Model({"left": model}))).lungs["left"].landmarks is None
    with np.load(path) as z:
        data = {k: z[k] for k in z.files if k != "lung/left/landmark_smoothing"}
    np.savez(tmp_path / "part.npz", **data)
    with pytest.raises(ModelFileError, match="only part of the landmark correction"):
        load_model(tmp_path / "part.npz")
    assert lung.oriented("prone").landmarks is None


def _check_tidal_linearity(lung_model):
    # Across the tidal range the enclosed volume at s units is V_EE + s·ΔV within 1 %.
    v0 = lung_model.volume_ee_ml
    worst = 0.0
    for s in np.linspace(0, lung_model.calibration_ml / lung_model.unit_ml, 21):
        want = v0 + s * lung_model.unit_ml
        got = lung_model.surface_at(scale=s).volume_ml
        worst = max(worst, abs(got - want) / want)
    assert worst <= 0.01
    return worst


def test_embedded_real_lungs_follow_500_ml(tmp_path):
    # The embedded lungs are real (Coronacases 001): 500 mL over both lungs, and each lung alone.
    from lungdeform.data import default_lungs
    from lungdeform.model.lung import build_model

    lungs = default_lungs()
    model = build_model(lungs, tidal_ml=500.0)
    for lung in model.lungs.values():
        _check_tidal_linearity(lung)
    single = build_lung(lungs["right"], "right", calibration_ml=500.0)
    _check_tidal_linearity(single)
    # directions and force are physical: every vertex moves outward-ish on average
    u = single.displacement
    assert np.einsum("ij,ij->i", u, single.surface.vertex_normals).mean() > 0


def test_real_itk_lung_follows_500_ml(data_dir):
    # Real data: the ITK right lung (smaller volume) from its mask, 500 mL tidal range.
    from lungdeform.io.meshfile import load
    from tests.conftest import require_path

    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    mask = sorted(p for p in folder.iterdir() if p.name.endswith("_mask.mha"))
    assert mask, f"no *_mask.mha in {folder}"
    surfaces = [s for m in mask for s, _ in load(m, target_vertices=4000)]
    smaller = min(surfaces, key=lambda s: s.volume_ml)
    assert 3000 < smaller.volume_ml < 3700  # data README: 3.36 L
    lung = build_lung(smaller, "right", calibration_ml=500.0)
    _check_tidal_linearity(lung)


def test_every_named_orientation_expands_real_lungs():
    # Directions take their origins on the side the lung rests on (paper's supine reasoning
    # applied to any position), so prone and both decubitus positions breathe too.
    from lungdeform.constants import GRAVITY
    from lungdeform.data import default_lungs
    from lungdeform.model.lung import build_model

    model = build_model(default_lungs())
    for name in GRAVITY:
        for lung in model.oriented(name).lungs.values():
            grown = lung.surface_at(scale=lung.calibration_ml / lung.unit_ml).volume_ml
            assert grown == pytest.approx(lung.volume_ee_ml + lung.calibration_ml, rel=1e-9)


def test_prone_directions_mirror_supine(left_lung):
    # Prone flips only the anterior–posterior axis of the directions.
    supine = build_lung(left_lung, "left")
    prone = supine.oriented("prone")
    frame = supine.frame.supported("prone")
    assert np.allclose(frame.axes[1], -supine.frame.axes[1]) and np.allclose(frame.axes[[0, 2]], supine.frame.axes[[0, 2]])
    assert np.all(prone.directions[:, 1] >= 0)  # now posterior (+y LPS) or zero
    assert np.allclose(prone.directions[:, [0, 2]] != 0, supine.directions[:, [0, 2]] != 0)
