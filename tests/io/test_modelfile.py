"""lungdeform.io.modelfile: the versioned model file round trip, older schemas read as made, bad files refused;
``load_model`` on damaged files: always a ModelFileError naming the file (the fuzzer's classes, kept in
tests/corpus/model/, made by tests/corpus/make_corpus.py)."""

from pathlib import Path

import numpy as np
import pytest

from lungdeform.errors import InputError, ModelFileError
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.io.modelfile import SCHEMA_VERSION, load_model, save_model
from lungdeform.model.lung import Model, build_lung


@pytest.fixture
def model(left_lung):
    # Table I: the sliding interior these format tests (older schemas, landmark corrections) start from
    return build_lung(left_lung, "left", default="paper")


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
    assert int(data["schema_version"]) == SCHEMA_VERSION == 6
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

    with pytest.raises(InputError, match="interior_vertices"):
        replace(model, interior_vertices=np.flatnonzero(keep))
    with pytest.raises(InputError, match="interior_kind"):
        replace(model, interior_kind="spline")


def _interior_map(rng, model):
    from lungdeform.interior.surface_map import SurfaceMapField

    c = model.surface.vertices[:40]
    return SurfaceMapField(0.01 * rng.normal(size=(3, 4)), np.c_[np.eye(3), rng.normal(size=3)], c,
                               rng.normal(size=(40, 3)), 80.0)


def test_interior_map_is_saved_and_plays_back_the_same(tmp_path, model, rng):
    # schema 4: a lung whose interior follows a surface-to-surface map keeps it through a file,
    # so its interior points move exactly as before saving (truth: the map evaluated directly)
    from dataclasses import replace

    lung = replace(model, interior_map=_interior_map(rng, model))
    back = load_model(save_model(tmp_path / "m.npz", Model({"left": lung}))).lungs["left"]
    q = model.surface.vertices.mean(axis=0) + rng.uniform(-10, 10, size=(12, 3))
    np.testing.assert_array_equal(back.interior.displacement(q), lung.interior_map(q))
    assert not np.allclose(back.interior.displacement(q), model.interior.displacement(q))


def test_partial_interior_map_is_refused(tmp_path, model, rng):
    # all five map arrays or none: a file with only some of them names the lung and what it has
    from dataclasses import replace

    path = save_model(tmp_path / "m.npz", Model({"left": replace(model, interior_map=_interior_map(rng, model))}))
    with np.load(path) as z:
        data = {k: z[k] for k in z.files if not k.endswith("interior_map_weights")}
    np.savez(tmp_path / "part.npz", **data)
    with pytest.raises(ModelFileError, match=r"part.npz: lung 'left' has only part of the interior map"):
        load_model(tmp_path / "part.npz")


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
    # why: a readable archive whose faces are text passes the shape checks; max() on text raised a
    # TypeError; it must come out as the package's error naming the file, the member and the kind expected
    s = icosphere(1, 1.0)
    lung = build_lung(Surface(s.vertices * [45.0, 70.0, 110.0] + [90.0, 20.0, -150.0], s.faces, "left"), "left",
                      default="paper")
    path = save_model(tmp_path / "m.npz", Model({"left": lung}))
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["lung/left/faces"] = arrays["lung/left/faces"].astype(str)
    np.savez(tmp_path / "text.npz", **arrays)
    with pytest.raises(ModelFileError, match=r"text\.npz: member 'lung/left/faces' holds <U\d+ values, expected integer"):
        load_model(tmp_path / "text.npz")


def _rewritten(tmp_path, lung, name: str, **changes):
    """The model file of ``lung`` saved again with its members ``changes`` (key → array) replaced."""
    path = save_model(tmp_path / "m.npz", Model({"left": lung}))
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update({k.replace("__", "/"): v for k, v in changes.items()})
    np.savez(tmp_path / name, **arrays)
    return tmp_path / name


@pytest.mark.parametrize("member, value, why", [
    ("lung__left__displacement", lambda a: a.astype(np.complex128) + 1e-3j, r"holds complex128 values, expected real"),
    ("lung__left__vertices", lambda a: a.astype(np.complex64), r"holds complex64 values, expected real"),
    ("lung__left__stiffness", lambda a: a.astype(object).astype(str), r"holds <U\d+ values, expected real"),
    ("lung__left__unit_ml", lambda a: np.array([float(a), 1.0]), r"has shape \(2,\), expected one value"),
    ("lung__left__gravity", lambda a: np.array([np.nan, 0.0, 1.0]), r"holds NaN or infinity"),
    ("lung__left__faces", lambda a: a.astype(np.float64), r"holds float64 values, expected integer"),
])
def test_model_arrays_of_the_wrong_kind_refused(tmp_path, model, member, value, why):
    # why: complex displacements were accepted (their imaginary part dropped without a word), and
    # values of another kind or shape met numpy's errors or casts; the error names the member
    with np.load(save_model(tmp_path / "src.npz", Model({"left": model}))) as z:
        original = z[member.replace("__", "/")]
    bad = _rewritten(tmp_path, model, "bad.npz", **{member: value(original)})
    with pytest.raises(ModelFileError, match=rf"bad\.npz: member '{member.replace('__', '/')}' {why}"):
        load_model(bad)


@pytest.mark.parametrize("provenance, entry", [
    ({"volumes_ml": [2000, 2500], "alignment": [{"applied": {"matrix": [1, 0, 0, 1]}}]}, r"alignment\[0\]\.applied\.matrix"),
    ({"volumes_ml": [2000, "x"]}, "volumes_ml"),
    ({"alignment": {"applied": 1}}, "alignment"),
    (["not", "an", "object"], "is not a JSON object"),
])
def test_model_provenance_that_playback_reads_is_checked(tmp_path, model, provenance, entry):
    # why: 'dvf --scan 1' reshaped a provenance matrix of 4 values to 4 x 4 and ended in a ValueError
    # traceback; the entries playback reads are checked when the file is loaded, naming the entry
    import json

    bad = _rewritten(tmp_path, model, "prov.npz", provenance=np.array(json.dumps(provenance)))
    with pytest.raises(ModelFileError, match=rf"prov\.npz: member 'provenance' .*{entry}"):
        load_model(bad)


def test_raw_zip_members_raise_model_file_error(tmp_path, model):
    # found by the fuzzer: a zip member without the .npy suffix comes back from numpy as raw bytes,
    # which ended in an AttributeError; it is a damaged model file, named as such
    import zipfile

    path = save_model(tmp_path / "m.npz", Model({"left": model}))
    bad = tmp_path / "raw.npz"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(bad, "w") as dst:
        for item in src.infolist():
            if item.filename == "schema_version.npy":  # the version as plain text, not an .npy array
                dst.writestr("schema_version", b"4")
            else:
                dst.writestr(item.filename, src.read(item.filename))
    with pytest.raises(ModelFileError, match=r"raw.npz: not a lungdeform model file \(member 'schema_version'"):
        load_model(bad)


def test_population_default_model_round_trips(tmp_path, left_lung, right_lung):
    # a model built with the population default carries its interior (extension + tapered prior) as an
    # interior map: saved and read back, points inside move the same, the prior is kept apart from the
    # map's affine part (schema 6), and the default is recorded
    from lungdeform.model.lung import build_model

    m = build_model({"left": left_lung, "right": right_lung})
    path = save_model(tmp_path / "m.npz", m)
    back = load_model(path)
    q = left_lung.vertices.mean(axis=0) + np.linspace(-30, 30, 7)[:, None] * [1.0, 0.5, 1.5]
    a, b = m.lungs["left"].interior_map, back.lungs["left"].interior_map
    assert b is not None and b.prior is not None and b.prior.width_mm == a.prior.width_mm
    np.testing.assert_array_equal(b.prior.affine, a.prior.affine)
    np.testing.assert_allclose(back.lungs["left"].interior.displacement(q), m.lungs["left"].interior.displacement(q),
                               rtol=0, atol=1e-12)
    with np.load(path) as z:
        assert z["lung/left/interior_map_prior"].shape == (3, 4) and float(z["lung/left/interior_map_prior_taper_mm"]) > 0
    assert back.provenance["default"] == m.provenance["default"]


def test_schema_5_lungs_built_with_a_prior_have_it_unfolded_and_tapered(tmp_path, left_lung, rng):
    # why: before schema 6 a built lung's population prior was folded into the map's affine part, where
    # it moved the lung's own surface (a warped lung breathed ~56 % of the model's volume). Read now,
    # such a lung plays as one built today (truth: the lung built here, saved with the prior folded in
    # as 0.9 saved it); a version-5 map that is not its displacement's extension (a fit's registration)
    # is read as made
    from dataclasses import replace

    from lungdeform.model.lung import build_model

    m = build_model({"left": left_lung})
    path = save_model(tmp_path / "m.npz", m)
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    folded = data.pop("lung/left/interior_map_prior")
    data.pop("lung/left/interior_map_prior_taper_mm")
    data["lung/left/interior_map_linear"] = data["lung/left/interior_map_linear"] + folded
    np.savez(tmp_path / "v5.npz", **dict(data, schema_version=np.array(5)))
    old, new = load_model(tmp_path / "v5.npz").lungs["left"], m.lungs["left"]
    np.testing.assert_allclose(old.interior_map.prior.affine, new.interior_map.prior.affine, rtol=0, atol=1e-12)
    q = left_lung.vertices.mean(axis=0) + rng.normal(scale=25.0, size=(30, 3))
    np.testing.assert_allclose(old.interior.displacement(q), new.interior.displacement(q), rtol=0, atol=1e-9)
    np.testing.assert_allclose(old.interior.displacement(left_lung.vertices), new.interior.displacement(left_lung.vertices),
                               rtol=0, atol=1e-9)
    fit_like = replace(new, interior_map=_interior_map(rng, new))
    with np.load(save_model(tmp_path / "f.npz", Model({"left": fit_like}))) as z:
        np.savez(tmp_path / "f5.npz", **dict({k: z[k] for k in z.files}, schema_version=np.array(5)))
    kept = load_model(tmp_path / "f5.npz").lungs["left"].interior_map
    assert kept.prior is None and np.array_equal(kept.linear, fit_like.interior_map.linear)


@pytest.mark.parametrize("key, value, what", [("side", "lefty", "side is 'lefty'"), ("unit_ml", 0.0, "unit_ml is 0.0"),
                                              ("calibration_ml", -5.0, "calibration_ml is -5.0")])
def test_side_and_units_are_checked(tmp_path, model, key, value, what):
    # a model whose side is not a lung, or whose unit volume is zero (export divided by it: a
    # ZeroDivisionError traceback), is refused naming the file, the lung and the member
    path = save_model(tmp_path / "m.npz", Model({"left": model}, {"source": "test"}))
    with np.load(path) as z:
        data = dict(z)
    data[f"lung/left/{key}"] = np.array(value)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **data)
    with pytest.raises(ModelFileError) as err:
        load_model(bad)
    assert str(bad) in str(err.value) and what in str(err.value)


def test_absurd_displacement_is_refused(tmp_path, model):
    # displacements of 1e300 mm played as a breath (overflow warnings, then exit 0) are refused at load
    path = save_model(tmp_path / "m.npz", Model({"left": model}, {"source": "test"}))
    with np.load(path) as z:
        data = dict(z)
    data["lung/left/displacement"] = data["lung/left/displacement"] * 1e300
    bad = tmp_path / "bad.npz"
    np.savez(bad, **data)
    with pytest.raises(ModelFileError, match="more than 1000 mm: not a breathing lung"):
        load_model(bad)


def test_model_file_says_what_a_wrong_file_is(tmp_path, model):
    # a new user's mistakes, each named for what it is (truth: the bytes written here): a text file or
    # a PNG is not a zip (it used to be called "Python objects", numpy's guess for any non-zip file),
    # a pickle is a pickle, a folder is a folder (it used to be "no such model file"), and an .npz
    # of other arrays lacks the 'schema' member (it used to say "schema None")
    (tmp_path / "bad.npz").write_text("x_mm,y_mm,z_mm\n1,2,3\n")
    (tmp_path / "scan.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(32))
    (tmp_path / "p.npz").write_bytes(b"\x80\x04\x95" + bytes(16))
    (tmp_path / "folder.npz").mkdir()
    np.savez(tmp_path / "other.npz", a=np.zeros(3), b=np.ones(2))
    data = dict(np.load(save_model(tmp_path / "m.npz", Model({"left": model}))))
    np.savez(tmp_path / "renamed.npz", **dict(data, schema=np.array("someone.else")))
    cases = {
        "bad.npz": "bad.npz: not a lungdeform model file (not a NumPy .npz archive: not a zip file)",
        "scan.png": "scan.png: not a lungdeform model file (not a NumPy .npz archive: not a zip file)",
        "p.npz": "p.npz: not a lungdeform model file (a Python pickle, not a NumPy .npz archive)",
        "folder.npz": "folder.npz: is a folder, not a model file (give the .npz that build, fit or demo wrote)",
        "other.npz": "other.npz: not a lungdeform model file (a NumPy .npz archive without the 'schema' member; "
                     "it holds 'a', 'b')",
        "renamed.npz": "renamed.npz: not a lungdeform model file (its 'schema' member is 'someone.else', "
                       "expected 'lungdeform.model')",
    }
    for name, message in cases.items():
        with pytest.raises(ModelFileError) as info:
            load_model(tmp_path / name)
        assert str(info.value) == f"{tmp_path / name}{message[len(name):]}", name


def test_the_scans_breathing_state_is_kept_and_older_files_are_end_exhale(tmp_path, model):
    # why: schema 5 records where the scan lies in the breath (an end-inhale scan is played out
    # below it); a version-4 file has no such keys and is an end-exhale scan; a version-5 file with
    # one key of the two, or a state that is not one, is refused naming the file
    from lungdeform.model.scan_state import ScanState
    path = save_model(tmp_path / "m.npz", Model({"left": model}, {}, ScanState("end-inhale", 500.0)))
    assert load_model(path).scan == ScanState("end-inhale", 500.0)
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    old = {k: v for k, v in data.items() if not k.startswith("scan_")}
    np.savez(tmp_path / "v4.npz", **dict(old, schema_version=np.array(4)))
    assert load_model(tmp_path / "v4.npz").scan == ScanState()
    np.savez(tmp_path / "half.npz", **{k: v for k, v in data.items() if k != "scan_above_ee_ml"})
    with pytest.raises(ModelFileError, match="half.npz: schema 6 needs both scan_state and scan_above_ee_ml"):
        load_model(tmp_path / "half.npz")
    for key, value, needle in (("scan_state", np.array("deep"), "scan state must be one of"),
                               ("scan_above_ee_ml", np.array(-1.0), "above end-exhale must be 0 to"),
                               ("scan_above_ee_ml", np.array("x"), "holds <U1 values")):
        np.savez(tmp_path / "bad.npz", **dict(data, **{key: value}))
        with pytest.raises(ModelFileError, match=needle):
            load_model(tmp_path / "bad.npz")
