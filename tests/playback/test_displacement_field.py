"""Displacement-field images of a model: convention, inverse, Jacobian, fade, scan states."""

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.errors import InputError
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.geometry.mesh import winding_numbers
from lungdeform.io.image import to_sitk
from lungdeform.model.lung import Model
from lungdeform.playback import displacement_field as D
from lungdeform.playback import voxel as V
from lungdeform.playback.schedule import VolumeTrace
from tests.browser.support import two_lungs

# the test ellipsoids: lungs at x = ±90 mm, 120 × 160 × 220 mm; this grid covers both with room
GRID = D.Grid((84, 90, 150), np.array([2.4, 2.4, 4.0]), np.array([-180.0, -108.0, -166.0]), np.eye(3))


@pytest.fixture(scope="module")
def model():
    return two_lungs(2)


@pytest.fixture(scope="module")
def forward(model):
    return D.displacement_field(model, GRID, 300.0)


@pytest.fixture(scope="module")
def inverse(model):
    return D.displacement_field(model, GRID, 300.0, inverse=True)


def _inside(model, rng, n=300):
    """Random points inside the lungs (mm LPS, end-exhale) and the lung of each."""
    out, names = [], []
    for name, lung in model.lungs.items():
        v = lung.surface.vertices
        q = rng.uniform(v.min(axis=0), v.max(axis=0), size=(n, 3))
        q = q[winding_numbers(q, v, lung.surface.faces) > 0.5]
        out.append(q)
        names += [name] * len(q)
    return np.concatenate(out), np.array(names)


def _transform(field, grid):
    return sitk.DisplacementFieldTransform(to_sitk(field.astype(np.float64), grid.spacing, grid.origin, grid.direction))


def test_forward_field_moves_points_as_points_at(model, forward, rng):
    # the convention: a point at x goes to x + u(x), exactly LungModel.points_at at the lung's scale
    # (track's), up to the lattice and the voxel interpolation (measured ≈ 0.05 mm here)
    q, names = _inside(model, rng)
    scales = D.state_scales(model, 300.0)
    expected = np.concatenate([model.lungs[n].points_at(q[names == n], scale=scales[n]) for n in model.lungs])
    t = _transform(forward.field, GRID)
    got = np.array([t.TransformPoint(tuple(map(float, p))) for p in q])
    moved = np.linalg.norm(expected - q, axis=1)
    assert moved.mean() > 3.0  # the state moves points by millimetres: the test means something
    assert np.abs(got - expected).max() < 0.2


def test_inverse_composed_with_forward_is_identity(model, forward, inverse, rng):
    # y → y + w(y) → that + u(that) must come back to y (fixed-point inverse; residual reported)
    assert inverse.inverse and inverse.info["inversion_residual_mm"] < 0.2
    y, _ = _inside(model, rng)
    fw, iw = _transform(forward.field, GRID), _transform(inverse.field, GRID)
    back = np.array([fw.TransformPoint(iw.TransformPoint(tuple(map(float, p)))) for p in y])
    assert np.linalg.norm(back - y, axis=1).max() < 0.3


def test_no_folding_and_zero_far_outside(model, forward, inverse):
    # the fade keeps x → x + u(x) one-to-one (margin ≥ 2.5 × the largest surface motion)
    assert 0.2 < forward.jacobian_min < 1.0 < forward.jacobian_max
    assert inverse.jacobian_min > 0.2
    # beyond the margin (plus a lattice step) the field is exactly zero: the grid's corner voxels
    assert np.all(forward.field[0, 0, :5] == 0) and np.all(forward.field[-1, -1, -5:] == 0)
    assert forward.info["margin_mm"] >= D.BASE_MARGIN_MM


def test_fade_is_continuous_across_the_surface():
    # a lung's own field inside; outside faded from 1 (C¹ smoothstep) to 0 at the margin
    assert D.fade([0.0, 12.5, 25.0, 40.0], 25.0).tolist() == [1.0, 0.5, 0.0, 0.0]
    f = [np.ones((3, 3)), 2 * np.ones((3, 3))]
    u = D.blended_field(f, [np.array([True, False, False]), np.zeros(3, bool)],
                        [np.array([0.0, 1e-9, 10.0]), np.array([50.0, 60.0, 10.0])], 25.0)
    assert np.allclose(u[0], 1.0) and np.allclose(u[1], 1.0, atol=1e-6)  # at the surface: lung 1's own
    # equidistant from both lungs: the mean of the two faded fields
    assert np.allclose(u[2], 1.5 * D.fade(10.0, 25.0))


def test_jacobian_of_a_linear_field_in_physical_units(rng):
    # u(x) = B x on an anisotropic, rotated grid: det(I + B) at every voxel, whatever the voxel size
    c, s = np.cos(0.3), np.sin(0.3)
    grid = D.Grid((6, 7, 8), np.array([0.7, 1.3, 2.5]), np.array([5.0, -3.0, 2.0]),
                  np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]))
    b = rng.uniform(-0.2, 0.2, (3, 3))
    m = np.eye(4)
    m[:3, :3] += b
    field = D.add_affine(np.zeros(grid.shape + (3,), np.float32), grid, m)
    det = D.jacobian_determinant(field, grid.spacing, grid.direction)
    assert np.allclose(det, np.linalg.det(np.eye(3) + b), atol=1e-4)


def test_blend_equals_its_array_form(rng):
    # why: the fused node loop (voxel.blend_nodes) must give the numbers of the array form it replaced
    # (fade, inverse squared distance normalised over the lungs, einsum), bit for bit, with nodes inside
    # a lung, beyond every margin (inf) and in between, for one to three lungs
    for lungs in (1, 2, 3):
        n = 5000
        f = [rng.normal(size=(n, 3)) * 5 for _ in range(lungs)]
        inside = [rng.random(n) < 0.3 for _ in range(lungs)]
        dist = [np.where(i, 0.0, np.where(rng.random(n) < 0.2, np.inf, rng.uniform(0, 60, n))) for i in inside]
        d = np.stack(dist)
        a = np.where(np.stack(inside), 1.0, D.fade(d, 38.0))
        d = np.where(np.stack(inside), 0.0, np.minimum(d, 1e6))
        phi = 1.0 / (d + 1e-6) ** 2
        phi /= phi.sum(axis=0, keepdims=True)
        assert np.array_equal(D.blended_field(f, inside, dist, 38.0), np.einsum("ln,lnc->nc", a * phi, np.stack(f)))


def test_lattice_points_are_the_world_of_its_indices(rng):
    # why: Lattice.points sums one term per index axis instead of Grid.world's product: the same
    # points (exactly on an axis-aligned grid, to rounding on an oblique one)
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    oblique = D.Grid((40, 50, 60), np.array([0.7, 1.1, 2.5]), np.array([-10.3, 20.7, -30.1]), q)
    for grid, tol in ((GRID, 0.0), (oblique, 1e-9)):
        lat = D.lattice(grid, grid.world(np.array([3.0, 4, 2])), grid.world(np.array([50.0, 40, 30])), 4.0)
        want = grid.world(lat.ijk())
        assert lat.points(grid).shape == want.shape and len(want) == np.prod(lat.dims)
        assert np.abs(lat.points(grid) - want).max() <= tol


def test_lattice_is_exact_for_affine_values():
    # trilinear interpolation reproduces an affine function of the index exactly
    lat = D.lattice(GRID, np.array([-100.0, -50, -100]), np.array([100.0, 50, 100]), 10.0)
    ijk = lat.ijk()
    vals = np.stack([ijk[:, 0], 2 * ijk[:, 1], ijk[:, 2] - ijk[:, 0]], axis=1).reshape(*lat.dims[::-1], 3)
    full = D.upsample(lat, vals, GRID)
    (i0, j0, k0), (i1, j1, k1) = lat.box
    k, j, i = np.meshgrid(np.arange(k0, k1), np.arange(j0, j1), np.arange(i0, i1), indexing="ij")
    assert np.allclose(full[k0:k1, j0:j1, i0:i1], np.stack([i, 2 * j, k - i], axis=-1), atol=1e-3)
    assert np.all(full[:k0] == 0)


def test_scan_state_reads_the_fit_provenance(model):
    # volumes_ml and the applied alignment (scan → model frame) as evaluate/pipeline.write_outputs stores them
    a = np.eye(4)
    a[:3, 3] = [1.0, 2.0, -30.0]
    fitted = Model(model.lungs, {"volumes_ml": [3000.0, 3500.0], "alignment": [{"applied": {"matrix": a.tolist()}}]})
    st = D.scan_state(fitted, 1)
    assert st.delta_ml == 500.0 and np.array_equal(st.alignment, a)
    rest = D.scan_state(fitted, 0)
    assert rest.delta_ml == 0.0 and rest.alignment is None
    with pytest.raises(InputError, match="--scan must be 0 to 1"):
        D.scan_state(fitted, 2)
    with pytest.raises(InputError, match="not written by 'lungdeform fit'"):
        D.scan_state(model, 1)


def test_aligned_field_lands_in_the_scan_frame(model, forward):
    # with an alignment A (scan → model frame), x goes to A⁻¹(x + u(x)): here a pure translation t,
    # so the field is the unaligned one minus t everywhere (far outside: exactly −t)
    a = np.eye(4)
    a[:3, 3] = [2.0, -1.0, 5.0]
    r = D.displacement_field(model, GRID, 300.0, alignment=a)
    assert np.allclose(r.field, forward.field - a[:3, 3], atol=1e-4)
    assert np.allclose(r.field[0, 0, 0], -a[:3, 3])


def test_phase_states_span_one_cycle():
    # a 4 s cosine breath repeated three times: N phases over one 4 s period, end-inhale first (as
    # 4-D CT numbers phases: 0 % end-inhale, 50 % end-exhale), or from the first sample on request
    t = np.linspace(0, 12, 601)
    trace = VolumeTrace(t, 250 * (1 - np.cos(2 * np.pi * t / 4.0)))
    states, period = D.phase_states(trace, 4)
    assert period == pytest.approx(4.0, rel=0.02)
    assert [round(s.delta_ml) for s in states] == pytest.approx([500, 250, 0, 250], abs=6)
    assert [round(s.delta_ml) for s in D.phase_states(trace, 4, "start")[0]] == pytest.approx([0, 250, 500, 250], abs=6)


def test_lattice_field_against_the_dense_exact_field(model, forward, rng):
    # dense reference: the exact interior field (LungModel.points_at, track's) at every voxel at least a
    # lattice cell inside a lung. Trilinear interpolation of a smooth field errs by at most
    # Σ_a h_a²/8 · max|∂²u/∂x_a²| (docs/RADIOTHERAPY.md), the second derivatives estimated by second
    # differences of the exact field with the lattice's own steps h_a about each voxel
    scales = D.state_scales(model, 300.0)
    h = np.array(forward.info["node_spacing_mm"])
    k, j, i = (a.ravel() for a in np.meshgrid(*[np.arange(0, n, 3) for n in GRID.shape], indexing="ij"))
    x = GRID.world(np.stack([i, j, k], axis=1))
    worst, checked = 0.0, 0
    for name, lung in model.lungs.items():
        s = lung.surface
        deep = (winding_numbers(x, s.vertices, s.faces) > 0.5)
        deep &= SurfaceDistance(s.vertices, s.faces).distance(x) > np.linalg.norm(h)
        q = x[deep]
        exact = lung.points_at(q, scale=scales[name]) - q
        # h_a²/8 · |∂²u/∂x_a²| by second differences along each axis a, per voxel and component
        terms = [np.abs(lung.points_at(q + e, scale=scales[name]) - 2 * (exact + q)
                        + lung.points_at(q - e, scale=scales[name])) / 8 for e in np.diag(h)]
        bound = sum(t.max() for t in terms) + 1e-3  # max|u''| over the deep voxels; 1e-3: float32 rounding
        got = forward.field[k[np.flatnonzero(deep)], j[np.flatnonzero(deep)], i[np.flatnonzero(deep)]]
        err = np.abs(got - exact).max()
        assert err <= bound, (name, err, bound)
        worst, checked = max(worst, err), checked + len(q)
    assert checked > 1000 and worst > 0  # the test means something: many voxels, not trivially exact


def test_fused_jacobian_equals_numpy_gradient(rng):
    # reference: det(I + ∇u) from numpy.gradient (central differences, one-sided at the edges) in
    # physical units on a rotated anisotropic grid, for a random smooth field; the fused pass's
    # minimum, maximum and folded count are those of the reference over the box
    c, s = np.cos(0.4), np.sin(0.4)
    grid = D.Grid((9, 10, 11), np.array([0.9, 1.4, 2.5]), np.zeros(3), np.array([[c, 0, -s], [0, 1.0, 0], [s, 0, c]]))
    z, y, x = np.meshgrid(*[np.linspace(0, 3, n) for n in grid.shape], indexing="ij")
    field = np.stack([np.sin(x + y), np.cos(z) * x, np.sin(y * z)], axis=-1).astype(np.float32) * 3.0
    d = [np.gradient(field.astype(float), axis=ax) for ax in (2, 1, 0)]
    inv = grid.direction / grid.spacing
    g = np.eye(3) + np.einsum("azyxc,ra->zyxcr", np.stack(d), inv)
    ref = np.linalg.det(g)
    assert D.jacobian_determinant(field, grid.spacing, grid.direction) == pytest.approx(ref, abs=1e-4)
    box = ((2, 1, 3), (9, 8, 7))
    sub = ref[3:7, 1:8, 2:9]
    lo, hi, folded = D.jacobian_range(field, grid, box)
    assert (lo, hi) == pytest.approx((sub.min(), sub.max()), abs=1e-4) and folded == int((sub <= 0).sum()) > 0


def test_active_values_equal_the_field_at_the_active_nodes(model, rng):
    # active_values evaluates each lattice row from its first to its last active node (a surface map
    # by its row kernel, other fields point by point); at the active nodes it must equal the interior
    # field at the nodes' world positions (1e-9 mm: the row kernel's rounding, tests/interior), zero elsewhere
    from lungdeform.interior.field import InteriorField
    from lungdeform.interior.surface_map import surface_extension

    lung = model.lungs["left"] if "left" in model.lungs else next(iter(model.lungs.values()))
    v = lung.surface.vertices
    mapped = InteriorField(surface_extension(v, lung.interior.displacement(v)))
    lat = D.lattice(GRID, v.min(axis=0) - 10.0, v.max(axis=0) + 10.0, 7.0)
    active = rng.random(tuple(lat.dims[::-1])) < 0.3
    nodes = GRID.world(lat.ijk())
    for interior in (lung.interior, mapped):
        got = D.active_values(interior, GRID, lat, active)
        flat = active.ravel()
        assert np.abs(got[flat] - interior.displacement(nodes[flat])).max() <= 1e-9
        assert flat.sum() > 100 and not got[~flat].any()


def test_jacobian_skips_only_voxels_where_nothing_moves(rng):
    # the fused pass gives a determinant of exactly 1, without arithmetic, to voxels more than one
    # voxel from every non-zero displacement in their row and the four rows beside it; reference:
    # numpy.gradient's determinant everywhere (exactly 1 where all differences are 0). A field that
    # moves only in a blob, touching the array's edge along i, and one isolated non-zero voxel
    grid = D.Grid((12, 13, 14), np.array([0.9, 1.4, 2.5]), np.zeros(3), np.eye(3))
    field = np.zeros(grid.shape + (3,), np.float32)
    field[3:8, 2:9, 9:] = rng.normal(scale=0.2, size=(5, 7, 5, 3))
    field[10, 11, 2] = (0.0, 0.0, -6.0)  # folds its neighbour at k = 9 (det 1 − 6 / (2 · 2.5))
    d = [np.gradient(field.astype(float), axis=ax) for ax in (2, 1, 0)]
    ref = np.linalg.det(np.eye(3) + np.einsum("azyxc,ra->zyxcr", np.stack(d), grid.direction / grid.spacing))
    got = D.jacobian_determinant(field, grid.spacing, grid.direction)
    assert got == pytest.approx(ref, abs=1e-5) and (got == 1.0).sum() > field.size // 6
    for box in (((0, 0, 0), (14, 13, 12)), ((8, 1, 2), (12, 9, 9)), ((10, 8, 0), (11, 9, 12))):
        (i0, j0, k0), (i1, j1, k1) = box
        sub = ref[k0:k1, j0:j1, i0:i1]
        lo, hi, folded = D.jacobian_range(field, grid, box)
        assert (lo, hi) == pytest.approx((sub.min(), sub.max()), abs=1e-5) and folded == int((sub <= 0).sum())
    assert D.jacobian_range(field, grid)[2] == 1


def test_zeroed_is_a_writable_zero_float32_array():
    # the field's output is allocated by an anonymous memory map (voxel.zeroed); it must behave as
    # numpy.zeros: all zero, float32, C-contiguous, writable, and survive its maker's scope
    from lungdeform.playback.voxel import zeroed

    a = zeroed((3, 4, 5, 3))
    assert a.dtype == np.float32 and a.shape == (3, 4, 5, 3) and a.flags.c_contiguous and a.flags.writeable
    assert not a.any()
    a[1, 2, 3] = (1.0, 2.0, 3.0)
    assert a.sum() == 6.0 and zeroed((0, 4, 5, 3)).shape == (0, 4, 5, 3)


def test_spans_the_fill_records_give_the_jacobian_of_the_field(rng):
    # the fill records per voxel row the span it wrote, and the Jacobian pass reads those spans instead
    # of scanning the field: over a lattice that moves only in part of its box, plus voxels changed
    # afterwards (as refine does, recorded by widen_spans), the range must equal the reference's
    # (numpy.gradient's determinant over the box) and the range from the spans measured on the field
    grid = D.Grid((14, 20, 22), np.array([0.9, 1.1, 2.5]), np.zeros(3), np.eye(3))
    lat = D.lattice(grid, np.array([3.0, 2.0, 5.0]), np.array([17.0, 18.0, 25.0]), 3.0)
    vals = np.zeros(tuple(lat.dims[::-1]) + (3,))
    vals[1:3, 1:4, 2:4] = rng.normal(scale=0.4, size=(2, 3, 2, 3))
    spans = V.no_spans(grid.shape)
    field = D.upsample(lat, vals, grid, None, spans)
    flat = np.ravel_multi_index(([4, 9], [16, 15], [5, 18]), grid.shape)  # two voxels far from the moving part
    field.reshape(-1, 3)[flat] += np.float32([[0.0, 0.0, -6.0], [0.3, 0.0, 0.0]])  # the first folds k = 3
    V.widen_spans(spans, flat, grid.shape)
    d = [np.gradient(field.astype(float), axis=ax) for ax in (2, 1, 0)]
    ref = np.linalg.det(np.eye(3) + np.einsum("azyxc,ra->zyxcr", np.stack(d), grid.direction / grid.spacing))
    (i0, j0, k0), (i1, j1, k1) = lat.box
    sub = ref[k0:k1, j0:j1, i0:i1]
    recorded = D.jacobian_range(field, grid, lat.box, spans)
    assert recorded == D.jacobian_range(field, grid, lat.box)
    assert recorded[:2] == pytest.approx((sub.min(), sub.max()), abs=1e-5) and recorded[2] == int((sub <= 0).sum())
    assert recorded[0] < 0 < recorded[2] and recorded[1] > 2.0  # set by the voxels changed after the fill


def test_aligned_jacobian_rows_are_the_general_rows_to_the_bit(rng):
    # reference: the general per-voxel row (_det_row, which also serves oblique grids) on an
    # axis-aligned grid; the vectorised row (columns, then determinants) must give the same float64
    # determinants bit for bit, inner voxels and the one-sided ends, at the array's edges (k, j = 0 and
    # the last) and inside, for rows that start and end anywhere (one voxel, two, the whole row)
    f = rng.normal(scale=0.7, size=(4, 5, 9, 3)).astype(np.float32)
    f[1, 2, 3:5] = 0.0  # exact zeros and a negative zero in the differences
    f[2, 2, 4, 1] = -0.0
    inv = np.diag([1 / 0.8, 1 / 1.3, 1 / 2.5])
    g = f.reshape(4, 5, 27)
    identity = np.zeros((3, 27))
    for c in range(3):
        identity[c, c::3] = 1.0
    work = (np.empty((3, 27)), identity)
    checked = 0
    for k in range(4):
        for j in range(5):
            for a, b in ((0, 9), (0, 1), (8, 9), (3, 4), (2, 7), (0, 2), (7, 9)):
                ref = V._det_row(f, k, j, (a, b), inv, np.empty(b - a), True)
                got = V._det_row_aligned(g, k, j, (a, b), inv, np.empty(b - a), work)
                assert np.array_equal(got.view(np.uint64), ref.view(np.uint64)), (k, j, a, b)
                checked += b - a
    assert checked == 20 * 21 and not np.all(ref == 1.0)


def test_a_fresh_fill_writes_the_bits_of_adding_to_zero(rng):
    # reference: the fill adding into a zero field (as add_affine adds into any field); written
    # into a fresh field (``fresh``: x + 0, no read of the untouched page) the output must be the same
    # bits, with and without an affine part, and the same spans. Negative zeros: a node of −0 beside
    # a negative one interpolates to −0 at its voxel (−0·1 + (−1)·0), which 0 + x makes +0
    grid = D.Grid((9, 12, 14), np.array([0.9, 1.1, 2.5]), np.zeros(3), np.eye(3))
    lat = D.lattice(grid, np.array([2.0, 2.0, 4.0]), np.array([11.0, 12.0, 20.0]), 3.0)
    shape = tuple(lat.dims[::-1]) + (3,)
    signed = np.full(shape, -0.0, np.float32)
    signed[1, 1, 1] = -1.0
    axes = tuple(V.axis_weights(grid.shape[2 - a], int(lat.lo[a]), int(lat.stride[a]), int(lat.dims[a]),
                                lat.box[0][a], lat.box[1][a]) for a in (2, 1, 0))
    (i0, j0, k0), (i1, j1, k1) = lat.box
    ranges = np.array([k0, k1, j0, j1, i0, i1], np.int64)
    for vals in (rng.normal(scale=0.4, size=shape).astype(np.float32), signed):
        for affine in ((np.zeros(3), np.zeros((3, 3))), (np.array([0.0, -0.0, 0.5]), np.eye(3) * -1e-3)):
            s_add, s_fresh = V.no_spans(grid.shape), V.no_spans(grid.shape)
            added = V.fill_field(np.zeros(grid.shape + (3,), np.float32), vals, axes, affine, ranges, s_add, False)
            fresh = V.fill_field(V.zeroed(grid.shape + (3,)), vals, axes, affine, ranges, s_fresh, True)
            assert np.array_equal(fresh.view(np.uint32), added.view(np.uint32))
            assert all(np.array_equal(a, b) for a, b in zip(s_add, s_fresh))
            assert (added < 0).any() and not np.signbit(added[added == 0]).any()
    row = np.zeros((shape[2], 3), np.float32)
    V._row(signed, 1, np.float32(0.0), 1, np.float32(0.0), row)
    assert np.signbit(row[0, 0]) and row[1, 0] == -1.0  # the −0 this test is about reaches the lerp
