"""lungdeform.bench.viewer: models of N vertices and the per-size record (a stub stands in for the browser;
timings are never asserted)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.bench.viewer import check_viewer_tools, model_with_vertices, upsampled, viewer_record
from lungdeform.errors import InputError
from lungdeform.playback.export import glb_bytes


@pytest.fixture(scope="module")
def small_model():
    return model_with_vertices(800)


def test_model_with_vertices_splits_the_total_between_the_lungs(small_model):
    # truth: each embedded lung (about 3000 vertices) is decimated to total/2 when that is fewer
    assert set(small_model.lungs) == {"left", "right"}
    for lung in small_model.lungs.values():
        assert abs(lung.n_vertices - 400) <= 5


def test_upsampled_interpolates_every_per_vertex_array(small_model):
    # truth: one midpoint subdivision keeps the old vertices first (V → 4V − 6, faces ×4) and gives
    # each new vertex the mean of its edge's ends; directions are renormalised to unit length
    lung = small_model.lungs["left"]
    up = upsampled(lung, 1)
    n = lung.n_vertices
    assert up.n_vertices == 4 * n - 6 and len(up.surface.faces) == 4 * len(lung.surface.faces)
    np.testing.assert_array_equal(up.surface.vertices[:n], lung.surface.vertices)
    np.testing.assert_array_equal(up.displacement[:n], lung.displacement)
    np.testing.assert_array_equal(up.stiffness[:n], lung.stiffness)
    np.testing.assert_allclose(np.linalg.norm(up.directions, axis=1), 1.0, rtol=1e-12)
    # a new vertex sits at an edge midpoint, and its stiffness is the mean of the two ends'
    new = up.surface.vertices[n]
    ends = np.flatnonzero(np.isclose(np.linalg.norm(lung.surface.vertices - new, axis=1),
                                     np.linalg.norm(lung.surface.vertices - new, axis=1).min(), rtol=1e-9))
    assert len(ends) == 2
    np.testing.assert_allclose(new, lung.surface.vertices[ends].mean(axis=0), rtol=1e-12)
    assert up.stiffness[n] == pytest.approx(lung.stiffness[ends].mean(), rel=1e-12)
    assert upsampled(lung, 0).n_vertices == n


def test_viewer_record_from_one_run(small_model):
    # truth: the record carries the glb the browser was given, the model's vertex count, and the CPU
    # playback figures of the same run (a ratio to a memory copy)
    seen = []

    def browser(glb: bytes) -> dict:
        seen.append(glb)
        return {"runs": []}

    row = viewer_record(small_model, browser, playback_frames=3)
    assert len(seen) == 1 and seen[0][:4] == b"glTF"
    assert row["glb_bytes"] == len(seen[0]) == len(glb_bytes(small_model))
    assert row["vertices"] == sum(lung.n_vertices for lung in small_model.lungs.values())
    assert row["viewer"] == {"runs": []}
    assert row["cpu_playback_step_ms"] > 0 and row["cpu_playback_ratio_to_memcpy"] > 0


def test_missing_viewer_tools_are_named(tmp_path):
    # an empty folder has no node_modules (and maybe no node): refused, naming the folder
    with pytest.raises(InputError, match=str(tmp_path)):
        check_viewer_tools(tmp_path)
