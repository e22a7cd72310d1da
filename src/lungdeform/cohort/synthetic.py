"""A synthetic cohort with known truth: lungs deformed by the model itself.

Every subject is made from a real lung shape shipped with lungdeform (Coronacases 001 left and
right, CC BY 4.0; the ITKElastix right lung, Apache-2.0), optionally varied by a random anisotropic
scale about its centroid, so that subjects differ. For each lung:

1. constants c1…c9 are drawn around Table I for its side (:func:`draw_constants`): c1…c6 by a
   log-normal factor, clipped into :data:`lungdeform.fit.fitting.DIRECTION_BOUNDS`; c7, c9 around Table I,
   c8 Table I; then c7…c9 are normalised as the fit reports them (largest ``|c|`` among them is 1);
2. the displacement ``u = k·F·d`` is built by :func:`lungdeform.model.lung.build_lung` (supine, uniform
   stiffness): directions from c1…c6, the force response of ``f = c7·x̂ + c8·ĥ + c9·ẑ`` through the
   spring-node graph, ``k`` calibrated exactly at the first volume change ΔV₁ with ``unit_ml = ΔV₁``.
   That is the form :class:`lungdeform.fit.objective.LungFitter` assumes (same frame, same force fields,
   same calibration), so the true constants give a zero-residual model for ``law="linear"``;
3. the larger-volume surfaces are ``p + s_j·u``. ``law="exact"`` (default): ``s_j`` is the root of
   the exact volume cubic (:func:`lungdeform.model.displacement.scale_for_volume`), so every surface
   encloses exactly ``V_EE + ΔV_j``; ``law="linear"``: ``s_j = ΔV_j/ΔV₁``, the fit's linear
   playback (volumes exact only at ΔV₁; the manifest then states the nominal volumes);
4. noise: each vertex of each larger-volume surface moves by ``ε·n`` with ``ε ~ N(0, noise_mm²)``
   along the clean surface's outward vertex normal ``n`` (seeded). The end-exhale surface, the
   model mesh, is kept exact;
5. optional landmarks: a seeded subset of surface vertices at their true (noise-free) positions at
   every volume, moved by the full displacement, tangential part included, which a surface
   distance cannot see. The interior field (the sliding interpolation of the normal motion) does
   not see it either: even the true model moves such landmarks about 0.5 mm (mean) off, and the
   interior landmark correction learns the rest;
6. optional table shift (``table_shift_mm`` > 0): each larger-volume surface and its landmarks are
   translated by a known random vector (N(0, table_shift_mm²) per axis), as a patient table
   between scans; drawn last, so a cohort without it is unchanged.

The files are in one frame (without a table shift: the end-exhale frame). Fit them with
``lungdeform cohort MANIFEST --align none`` (or ``--align joint``, which must then recover the
table shift): the default apex alignment assumes that the apex cap and a posterior band do not
move, but the model moves them, so it shifts these targets by several millimetres.

Every random draw of one lung comes from ``numpy.random.default_rng([seed, subject_index, side_index])``:
adding subjects never changes the earlier ones. Library functions return data; :func:`write_cohort`
writes the files (atomically) and returns where they went.
"""

from __future__ import annotations

import csv
import io as _io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from lungdeform import __version__, data
from lungdeform.atomic import write_json, write_npz, write_text
from lungdeform.constants import table_constants
from lungdeform.errors import InputError, ReadError
from lungdeform.fit.fitting import DIRECTION_HI, DIRECTION_LO
from lungdeform.geometry.mesh import Surface, vertex_normals
from lungdeform.io.landmarks import write_elastix_points
from lungdeform.io.meshfile import write_mesh
from lungdeform.model.displacement import scales_for_volumes, volume_polynomial
from lungdeform.model.lung import BuildSettings, build_lung
from lungdeform.progress import Progress, silent

TRUTH_SCHEMA = "lungdeform.synthetic.truth"
TRUTH_VERSION = 1
LAWS = ("exact", "linear")
SIDE_INDEX = {"left": 0, "right": 1}


@dataclass(frozen=True)
class SourceShape:
    """A real lung shape shipped with lungdeform, used as a synthetic subject's end-exhale surface."""

    name: str
    side: str
    licence: str
    attribution: str

    def load(self) -> Surface:
        if self.name == "itk_right_lung":
            return data.itk_right_lung()
        return data.default_lungs()[self.side]


_CORONA = ("COVID-19 CT Lung and Infection Segmentation Dataset, Ma J. et al., Zenodo 2020 "
           "(doi:10.5281/zenodo.3757476); lobe labels by A. Creegan (lung_modelling); case 001")
SOURCES: dict[str, SourceShape] = {
    "coronacases_001_left": SourceShape("coronacases_001_left", "left", "CC BY 4.0", _CORONA),
    "coronacases_001_right": SourceShape("coronacases_001_right", "right", "CC BY 4.0", _CORONA),
    "itk_right_lung": SourceShape("itk_right_lung", "right", "Apache-2.0",
                                  "ITKElastix example data (InsightSoftwareConsortium/ITKElastix), "
                                  "right lung, smaller-volume mask"),
}


def subject_sources(index: int) -> dict[str, str]:
    """``{side: source name}`` for subject ``index``: Coronacases left always; the right lung
    alternates between Coronacases (even index) and the ITK lung (odd index)."""
    return {"left": "coronacases_001_left",
            "right": "coronacases_001_right" if index % 2 == 0 else "itk_right_lung"}


# --------------------------------------------------------------------------- free functions
def normalise_force_constants(constants) -> np.ndarray:
    """c1…c9 ``(9,) float`` with c7…c9 divided by their largest ``|c|`` (the fit's convention)."""
    c = np.array(constants, dtype=float)
    if c.shape != (9,) or not np.all(np.isfinite(c)):
        raise InputError(f"constants must be 9 finite values c1…c9, got shape {c.shape}")
    scale = np.abs(c[6:]).max()
    if not scale > 0:
        raise InputError("constants: c7…c9 are all zero (no applied force)")
    c[6:] /= scale
    return c


def draw_constants(side: str, rng: np.random.Generator, *, spread: float = 0.2,
                   force_spread: float = 0.05) -> np.ndarray:
    """Random c1…c9 ``(9,) float`` around Table I for ``side``.

    c1…c6 = Table I × exp(N(0, spread²)), clipped into the fit's bounds
    (:data:`lungdeform.fit.fitting.DIRECTION_BOUNDS`); c7, c9 = |Table I + N(0, force_spread²)|, c8 = Table I;
    c7…c9 normalised (:func:`normalise_force_constants`), so c8 = 1 while it dominates.
    """

    if not (spread >= 0 and force_spread >= 0):
        raise InputError(f"spread and force_spread must be >= 0, got {spread!r}, {force_spread!r}")
    t = table_constants(side)
    c = t.copy()
    c[:6] = np.clip(t[:6] * np.exp(rng.normal(0.0, spread, 6)), DIRECTION_LO, DIRECTION_HI)
    c[6] = abs(t[6] + rng.normal(0.0, force_spread))
    c[8] = abs(t[8] + rng.normal(0.0, force_spread))
    return normalise_force_constants(c)


def scaled_shape(surface: Surface, factors) -> Surface:
    """``surface`` scaled by ``factors : (3,)`` (x, y, z in LPS, all > 0) about its vertex centroid."""
    f = np.asarray(factors, float)
    if f.shape != (3,) or not np.all(f > 0):
        raise InputError(f"scale factors must be 3 positive numbers, got {factors!r}")
    c = surface.vertices.mean(axis=0)
    return Surface(c + (surface.vertices - c) * f, surface.faces, surface.name)


def model_displacement(surface: Surface, side: str, constants, unit_ml: float, *, gravity="supine") -> np.ndarray:
    """``u : (n, 3) float``, mm per ``unit_ml``, LPS: the model's displacement ``k·F·d`` for
    c1…c9, calibrated so that ``p + u`` encloses exactly ``V_EE + unit_ml``
    (:func:`lungdeform.model.lung.build_lung`, uniform stiffness)."""

    if not unit_ml > 0:
        raise InputError(f"unit_ml must be > 0 mL, got {unit_ml!r}")
    lung = build_lung(surface, side, constants=np.asarray(constants, float), gravity=gravity,
                      settings=BuildSettings(float(unit_ml), float(unit_ml)))
    return lung.displacement


def volume_scales(surface: Surface, displacement: np.ndarray, delta_ml, unit_ml: float, law: str = "exact") -> np.ndarray:
    """``s : (k,) float`` units of ``displacement`` for volume changes ``delta_ml : (k,)`` mL.

    ``law="exact"``: ``V(p + s·u) = V_EE + ΔV`` exactly (cubic root); ``"linear"``: ``s = ΔV/unit_ml``.
    """

    if law not in LAWS:
        raise InputError(f"law must be one of {', '.join(LAWS)}, got {law!r}")
    dv = np.asarray(delta_ml, float)
    if law == "linear":
        return dv / float(unit_ml)
    poly = volume_polynomial(surface.vertices, surface.faces, displacement)
    return scales_for_volumes(poly, dv)


def normal_noise(vertices: np.ndarray, faces: np.ndarray, sigma_mm: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``(noisy (n, 3) mm, offsets (n,) mm)``: each vertex moved by ``ε ~ N(0, sigma_mm²)`` along its
    outward vertex normal."""
    if not (np.isfinite(sigma_mm) and sigma_mm >= 0):
        raise InputError(f"noise must be a finite SD >= 0 mm, got {sigma_mm!r}")
    v = np.asarray(vertices, float)
    eps = rng.normal(0.0, float(sigma_mm), len(v)) if sigma_mm > 0 else np.zeros(len(v))
    return np.ascontiguousarray(v + eps[:, None] * vertex_normals(v, faces)), eps


# --------------------------------------------------------------------------- one synthetic lung
@dataclass(frozen=True, eq=False)
class SyntheticLung:
    """One synthetic lung with its truth.

    Attributes
    ----------
    subject, side : str
    source : str
        Key of :data:`SOURCES` the end-exhale shape came from.
    rest : Surface
        End-exhale surface ``p`` (noise-free), mm LPS.
    constants : (9,) float
        True c1…c9 (c7…c9 normalised as the fit reports them).
    displacement : (n, 3) float
        True ``u``, mm per ``unit_ml``, LPS.
    unit_ml : float
        ΔV₁ (mL): ``p + u`` encloses exactly ``V_EE + unit_ml``.
    delta_ml : (k,) float
        Volume changes of the larger surfaces above end-exhale, mL (nominal).
    scales : (k,) float
        ``s_j``: the clean surface j is ``p + s_j·u``.
    noise : (k, n) float
        Normal offsets (mm) added to each vertex of each larger surface.
    noise_mm : float
        Requested noise SD, mm.
    scale_factors : (3,) float
        Anisotropic scale applied to the source shape (x, y, z).
    landmark_index : (m,) int
        Vertices used as landmarks (may be empty).
    seed : tuple of int
        The generator's seed sequence entropy.
    law : 'exact' | 'linear'
    table_shifts : (k, 3) float or None
        Translation (mm) of each larger-volume scan (surface and landmarks); None: no shift.
    """

    subject: str
    side: str
    source: str
    rest: Surface
    constants: np.ndarray
    displacement: np.ndarray
    unit_ml: float
    delta_ml: np.ndarray
    scales: np.ndarray
    noise: np.ndarray
    noise_mm: float
    scale_factors: np.ndarray
    landmark_index: np.ndarray
    seed: tuple
    law: str = "exact"
    table_shifts: np.ndarray | None = None

    @property
    def volume_ee_ml(self) -> float:
        return self.rest.volume_ml

    @property
    def volumes_ml(self) -> np.ndarray:
        """``(k + 1,) float`` mL: end-exhale, then the nominal target volumes ``V_EE + ΔV_j``."""
        return np.concatenate([[self.volume_ee_ml], self.volume_ee_ml + self.delta_ml])

    def clean_vertices(self, j: int) -> np.ndarray:
        """``(n, 3) float`` mm: the noise-free surface j, ``p + s_j·u``."""
        return np.ascontiguousarray(self.rest.vertices + self.scales[j] * self.displacement)

    def shift(self, j: int) -> np.ndarray:
        """``(3,) float`` mm: the table shift of scan j (zeros without one)."""
        return np.zeros(3) if self.table_shifts is None else np.asarray(self.table_shifts[j], float)

    def target(self, j: int) -> Surface:
        """The noisy larger-volume surface j (mm LPS), table shift included."""
        v = self.clean_vertices(j)
        noisy = v + self.noise[j][:, None] * vertex_normals(v, self.rest.faces) + self.shift(j)
        return Surface(noisy, self.rest.faces, f"{self.subject}_{self.side}_dv{self.delta_ml[j]:g}")

    def landmarks(self, j: int | None) -> np.ndarray:
        """``(m, 3) float`` mm: landmark positions at end-exhale (``j=None``) or at target j (noise-free,
        table shift included)."""
        v = self.rest.vertices if j is None else self.clean_vertices(j) + self.shift(j)
        return np.ascontiguousarray(v[self.landmark_index])


def _check_deltas(delta_ml) -> np.ndarray:
    dv = np.asarray(delta_ml, float).reshape(-1)
    if len(dv) == 0 or not np.all(np.isfinite(dv)) or np.any(dv <= 0) or np.any(np.diff(dv) <= 0):
        raise InputError(f"volume changes must be positive and strictly increasing (mL), got {list(delta_ml)!r}")
    return dv


@dataclass(frozen=True)
class SyntheticLungSpec:
    """What :func:`synthesize_lung` makes of a shape: ``noise_mm`` the SD of the normal surface noise
    (mm); ``law`` the volume law (:data:`LAWS`); ``landmarks`` how many surface vertices are kept as
    landmarks; ``table_shift_mm`` the SD per axis of a random translation of each larger-volume scan
    (mm, 0: none)."""

    noise_mm: float = 0.0
    law: str = "exact"
    landmarks: int = 0
    table_shift_mm: float = 0.0


@dataclass(frozen=True)
class SyntheticOrigin:
    """Where a synthetic lung came from, recorded in its truth: ``subject``; ``source`` (a key of
    :data:`SOURCES`); the ``scale_factors (3,)`` applied to the shape; the RNG ``seed``."""

    subject: str = "synthetic"
    source: str = ""
    scale_factors: tuple = (1.0, 1.0, 1.0)
    seed: tuple = ()


def synthesize_lung(surface: Surface, side: str, constants, delta_ml: Sequence[float], *,
                    rng: np.random.Generator, spec: SyntheticLungSpec = SyntheticLungSpec(),
                    origin: SyntheticOrigin = SyntheticOrigin()) -> SyntheticLung:
    """Deform ``surface`` (end-exhale, mm LPS) by the model with ``constants`` to the volume changes
    ``delta_ml`` (mL above end-exhale, increasing), add normal noise, pick landmarks (``spec``). See
    the module docstring for the steps."""
    noise_mm, law, landmarks, table_shift_mm = spec.noise_mm, spec.law, spec.landmarks, spec.table_shift_mm
    subject, source, scale_factors, seed = origin.subject, origin.source, origin.scale_factors, origin.seed
    dv = _check_deltas(delta_ml)
    if landmarks < 0 or landmarks > surface.n_vertices:
        raise InputError(f"landmarks must be between 0 and {surface.n_vertices}, got {landmarks}")
    c = normalise_force_constants(constants)
    u = model_displacement(surface, side, c, dv[0])
    s = volume_scales(surface, u, dv, dv[0], law)
    noise = np.zeros((len(dv), surface.n_vertices))
    for j in range(len(dv)):
        _, noise[j] = normal_noise(surface.vertices + s[j] * u, surface.faces, noise_mm, rng)
    idx = np.sort(rng.choice(surface.n_vertices, landmarks, replace=False)) if landmarks else np.zeros(0, int)
    if not (np.isfinite(table_shift_mm) and table_shift_mm >= 0):
        raise InputError(f"table_shift_mm must be a finite SD >= 0 mm, got {table_shift_mm!r}")
    shifts = rng.normal(0.0, float(table_shift_mm), (len(dv), 3)) if table_shift_mm > 0 else None
    return SyntheticLung(subject, side, source, surface, c, u, float(dv[0]), dv, s, noise, float(noise_mm),
                         np.asarray(scale_factors, float), idx.astype(np.int64), tuple(seed), law, shifts)


#: The default of :func:`synthetic_cohort`: no noise, the exact law, 50 landmarks per lung, no table shift.
COHORT_SPEC = SyntheticLungSpec(landmarks=50)


def synthetic_cohort(n_subjects: int = 4, *, delta_ml: Sequence[float] = (300.0, 500.0),
                     spec: SyntheticLungSpec = COHORT_SPEC, seed: int = 0, spread: float = 0.2,
                     shape_spread: float = 0.1, sides: Sequence[str] = ("left", "right"),
                     progress: Progress | None = None) -> list[SyntheticLung]:
    """``n_subjects`` synthetic subjects, one :class:`SyntheticLung` per side, each made with ``spec``
    (default :data:`COHORT_SPEC`: 50 landmarks, no noise).

    Shapes: :func:`subject_sources`, each scaled by factors drawn uniformly in
    ``1 ± shape_spread`` per axis; constants: :func:`draw_constants` with ``spread``; table shifts
    of the larger-volume scans: N(0, table_shift_mm²) per axis (0: none).
    """
    say = progress or silent
    law, noise_mm = spec.law, spec.noise_mm
    if int(n_subjects) != n_subjects or n_subjects < 1:
        raise InputError(f"the number of subjects must be a positive integer, got {n_subjects!r}")
    if not 0 <= shape_spread < 1:
        raise InputError(f"shape_spread must be in [0, 1), got {shape_spread!r}")
    bad = [s for s in sides if s not in SIDE_INDEX]
    if bad or not sides:
        raise InputError(f"sides must be 'left' and/or 'right', got {list(sides)!r}")
    if law not in LAWS:
        raise InputError(f"law must be one of {', '.join(LAWS)}, got {law!r}")
    if not (np.isfinite(noise_mm) and noise_mm >= 0):
        raise InputError(f"noise must be a finite SD >= 0 mm, got {noise_mm!r}")
    _check_deltas(delta_ml)
    lungs = []
    for i in range(int(n_subjects)):
        subject = f"synth{i:03d}"
        for side in sides:
            key = (int(seed), i, SIDE_INDEX[side])
            rng = np.random.default_rng(key)
            src = SOURCES[subject_sources(i)[side]]
            factors = rng.uniform(1.0 - shape_spread, 1.0 + shape_spread, 3)
            shape = scaled_shape(src.load(), factors).with_name(f"{subject}_{side}_ee")
            c = draw_constants(side, rng, spread=spread)
            say(f"{subject} {side}: {src.name}, {shape.volume_ml:.0f} mL")
            origin = SyntheticOrigin(subject, src.name, factors, key)
            lungs.append(synthesize_lung(shape, side, c, delta_ml, rng=rng, spec=spec, origin=origin))
    return lungs


# --------------------------------------------------------------------------- files
def truth_record(lung: SyntheticLung, files: dict) -> dict:
    """The JSON truth of one lung (see :func:`write_cohort`)."""
    src = SOURCES.get(lung.source)
    enclosed = [Surface(lung.clean_vertices(j), lung.rest.faces).volume_ml for j in range(len(lung.delta_ml))]
    noisy = [lung.target(j).volume_ml for j in range(len(lung.delta_ml))]
    return {
        "subject": lung.subject, "side": lung.side,
        "source": lung.source, "licence": src.licence if src else None,
        "attribution": src.attribution if src else None,
        "scale_factors": lung.scale_factors.tolist(),
        "constants": lung.constants.tolist(),
        "volume_ee_ml": lung.volume_ee_ml,
        "delta_ml": lung.delta_ml.tolist(),
        "volumes_ml": lung.volumes_ml.tolist(),
        "enclosed_volumes_ml": enclosed,
        "noisy_volumes_ml": noisy,
        "scales": lung.scales.tolist(),
        "unit_ml": lung.unit_ml,
        "law": lung.law,
        "noise_mm": lung.noise_mm,
        "noise_sd_measured_mm": [float(np.std(e)) for e in lung.noise],
        "table_shifts_mm": None if lung.table_shifts is None else np.asarray(lung.table_shifts).tolist(),
        "displacement_rms_mm": float(np.sqrt(np.mean(np.sum((lung.scales[-1] * lung.displacement) ** 2, axis=1)))),
        "seed": list(lung.seed),
        "files": files,
    }


def write_cohort(lungs: Sequence[SyntheticLung], out, *, seed: int | None = None,
                 progress: Progress | None = None) -> dict:
    """Write surfaces (binary PLY, float64), landmark files, ``truth/<subject>_<side>.npz``,
    ``manifest.csv`` (``subject,side,volume_ml,path[,landmarks]``, paths relative to ``out``) and
    ``truth.json`` into the folder ``out``, every file atomically. Returns
    ``{"manifest": Path, "truth": Path, "files": int, "rows": int}``.

    The truth arrays (``.npz``): ``vertices (n, 3)``, ``faces (m, 3)``, ``displacement (n, 3)`` mm
    per ``unit_ml``, ``scales (k,)``, ``noise (k, n)`` mm, ``landmark_index (m,)``.
    """

    say = progress or silent
    if not lungs:
        raise InputError("no synthetic lungs to write")
    out = Path(out)
    keys = [(lung.subject, lung.side) for lung in lungs]
    if len(set(keys)) != len(keys):
        raise InputError("synthetic lungs: duplicated (subject, side)")
    with_lm = any(len(lung.landmark_index) for lung in lungs)
    rows, records, count = [], [], 0
    for lung in lungs:
        stem = f"{lung.subject}_{lung.side}"
        names = ["ee"] + [f"dv{d:g}" for d in lung.delta_ml]
        surfaces = [lung.rest] + [lung.target(j) for j in range(len(lung.delta_ml))]
        files = {"surfaces": [], "landmarks": [], "arrays": f"truth/{stem}.npz"}
        for j, (name, surf, vol) in enumerate(zip(names, surfaces, lung.volumes_ml)):
            rel = f"surfaces/{stem}_{name}.ply"
            write_mesh(out / rel, surf.vertices, surf.faces)
            files["surfaces"].append(rel)
            row = {"subject": lung.subject, "side": lung.side, "volume_ml": f"{vol:.6f}", "path": rel}
            if with_lm:
                lrel = f"landmarks/{stem}_{name}.txt"
                write_elastix_points(out / lrel, lung.landmarks(None if j == 0 else j - 1))
                files["landmarks"].append(lrel)
                row["landmarks"] = lrel
                count += 1
            rows.append(row)
            count += 1
        write_npz(out / files["arrays"], {"vertices": lung.rest.vertices, "faces": lung.rest.faces,
                                          "displacement": lung.displacement, "scales": lung.scales, "noise": lung.noise,
                                          "landmark_index": lung.landmark_index, "constants": lung.constants})
        count += 1
        records.append(truth_record(lung, files))
        say(f"wrote {stem}")
    buf = _io.StringIO()
    fields = ["subject", "side", "volume_ml", "path"] + (["landmarks"] if with_lm else [])
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    manifest = write_text(out / "manifest.csv", buf.getvalue())
    truth = write_json(out / "truth.json", {
        "schema": TRUTH_SCHEMA, "version": TRUTH_VERSION, "generator": f"lungdeform {__version__}",
        "seed": seed, "law": lungs[0].law, "noise_mm": lungs[0].noise_mm,
        "delta_ml": lungs[0].delta_ml.tolist(),
        "notes": ("Synthetic lungs deformed by the lungdeform model itself (u = k·F·d, supine, uniform "
                  "stiffness, calibrated exactly at the first volume change). The end-exhale surface is "
                  "exact; larger-volume surfaces carry Gaussian noise along the vertex normal. "
                  "Landmarks are surface vertices at their true, noise-free positions. volumes_ml are "
                  "the manifest's (nominal) volumes. The files are in one frame (larger-volume scans "
                  "moved by table_shifts_mm where given): fit with `lungdeform cohort manifest.csv "
                  "--align none` (no table shift) or `--align joint`; the default apex alignment "
                  "assumes that the apex does not move, which the model contradicts."),
        "cohort_command": ("lungdeform cohort manifest.csv --out OUT --align "
                           + ("joint" if any(lung.table_shifts is not None for lung in lungs) else "none")),
        "sources": {k: {"side": v.side, "licence": v.licence, "attribution": v.attribution}
                    for k, v in SOURCES.items() if any(lung.source == k for lung in lungs)},
        "lungs": records,
    })
    return {"manifest": manifest, "truth": truth, "files": count + 2, "rows": len(rows)}


def read_truth(path) -> dict:
    """Read ``truth.json``; returns ``{(subject, side): record}`` plus the header under ``None``.

    Raises :class:`lungdeform.errors.ReadError` naming the file for a wrong schema or a broken file.
    """


    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ReadError(f"{path}: cannot read the synthetic truth ({exc})") from exc
    if not isinstance(data, dict) or data.get("schema") != TRUTH_SCHEMA or data.get("version") != TRUTH_VERSION:
        raise ReadError(f"{path}: not a lungdeform synthetic truth file (schema {TRUTH_SCHEMA} v{TRUTH_VERSION})")
    out: dict = {None: {k: v for k, v in data.items() if k != "lungs"}}
    for rec in data.get("lungs", []):
        try:
            key = (str(rec["subject"]), str(rec["side"]))
            if len(rec["constants"]) != 9:
                raise ValueError("constants must have 9 values")
        except (KeyError, TypeError, ValueError) as exc:
            raise ReadError(f"{path}: a lung record is malformed ({exc})") from exc
        out[key] = rec
    return out
