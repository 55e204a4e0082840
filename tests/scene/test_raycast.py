"""Ray casting against analytic answers: tilted planes, spheres, boxes, extruded text."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.scene.model import rotation_matrix
from cdma_lidar.scene.raycast import cast, glyph_polygons
from cdma_lidar.scene.scenefile import parse_scene
from cdma_lidar.scene.truth import compute_truth


def _scene(*objects):
    return parse_scene({"instrument": {"wavelengths": {"count": 2}, "rotations_deg": [0.0, 1.0]},
                        "objects": list(objects)})


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@given(distance=st.floats(0.5, 50.0), yaw=st.floats(-60.0, 60.0), pitch=st.floats(-60.0, 60.0),
       refl=st.floats(0.0, 1.0))
def test_tilted_plane_distance_and_lambertian_cosine(distance, yaw, pitch, refl):
    scene = _scene({"kind": "plane", "position_m": [distance, 0.0, 0.0],
                    "orientation_deg": [yaw, pitch, 0.0], "reflectivity": refl})
    normal = rotation_matrix(np.array([yaw, pitch, 0.0]))[:, 0]
    rng = np.random.default_rng(1)
    dirs = _unit(np.column_stack([np.ones(64), rng.uniform(-0.1, 0.1, (64, 2))]))
    hits = cast(scene, dirs)
    # analytic: the plane n.x = n.p, ray x = t d  ->  t = (n.p) / (n.d)
    t = (normal @ np.array([distance, 0.0, 0.0])) / (dirs @ normal)
    expect = np.where(t > 0, t, np.nan)
    np.testing.assert_allclose(hits.range_m, expect, rtol=1e-12)
    seen = np.isfinite(expect)
    np.testing.assert_allclose(hits.cos_incidence[seen], np.abs(dirs @ normal)[seen], rtol=1e-12)
    np.testing.assert_allclose(hits.point_m[seen], dirs[seen] * t[seen, None], rtol=1e-9,
                               atol=1e-12)
    assert np.all(hits.reflectivity[seen] == refl)
    assert np.all(hits.object_id[~seen] == -1)


def test_sphere_and_box_and_nearest_wins():
    scene = _scene(
        {"kind": "plane", "position_m": [10.0, 0.0, 0.0]},
        {"kind": "sphere", "position_m": [4.0, 0.0, 0.0], "radius_m": 0.5},
        {"kind": "box", "position_m": [3.0, 1.0, 0.0], "size_m": [0.2, 0.4, 0.4],
         "orientation_deg": [0.0, 0.0, 0.0]},
    )
    dirs = _unit([[1.0, 0.0, 0.0], [1.0, 0.3 / 4.0, 0.0], [3.0, 1.0, 0.0], [-1.0, 0.0, 0.1]])
    hits = cast(scene, dirs)
    assert hits.object_id.tolist() == [1, 1, 2, -1]
    assert np.isclose(hits.range_m[0], 3.5)
    # the off-axis ray through the sphere: |t d - c|^2 = r^2
    p = hits.point_m[1]
    assert np.isclose(np.linalg.norm(p - [4.0, 0.0, 0.0]), 0.5)
    # the box's front face at x = 2.9, ray towards (3, 1): t = 2.9 / d_x
    assert np.isclose(hits.range_m[2], 2.9 / dirs[2, 0])
    assert np.isclose(hits.cos_incidence[2], dirs[2, 0])
    assert np.isnan(hits.range_m[3]) and np.all(np.isnan(hits.point_m[3]))


def test_ray_from_inside_a_sphere_hits_its_far_side():
    scene = _scene({"kind": "sphere", "position_m": [0.0, 0.0, 0.0], "radius_m": 2.0})
    hits = cast(scene, _unit([[1.0, 0.2, 0.1]]))
    assert np.isclose(hits.range_m[0], 2.0)


def test_text_is_filled_even_odd_and_centred():
    polys = glyph_polygons("O", "DejaVu Sans", 0.1)
    allpts = np.concatenate(polys)
    assert np.isclose(allpts[:, 1].max() - allpts[:, 1].min(), 0.1)
    scene = _scene({"kind": "text", "text": "O", "position_m": [5.0, 0.0, 0.0],
                    "height_m": 0.1})
    # through the middle of the "O" is its counter (a hole); through the left stroke is ink
    stroke_u = allpts[:, 0].min() + 0.004
    dirs = _unit([[5.0, 0.0, 0.0], [5.0, -stroke_u, 0.0], [5.0, 0.0, 0.2]])
    hits = cast(scene, dirs)
    assert hits.object_id.tolist() == [-1, 0, -1]
    assert np.isclose(hits.point_m[1, 0], 5.0)


def test_paper_scene1_truth_has_three_depths_and_empty_space():
    from cdma_lidar.scene import load_scene

    truth = compute_truth(load_scene("paper-scene1"))
    h = truth.hits
    assert h.range_m.shape == (40, 160)
    lit = h.lit
    assert 0.05 < lit.mean() < 0.5  # letters, and empty space elsewhere
    assert np.all(np.isnan(h.range_m[~lit]))
    per_object = [np.nanmedian(h.range_m[h.object_id == i]) for i in range(3)]
    assert np.all(np.diff(per_object) > 0.1)  # three range clusters
    assert 4.7 < min(per_object) and max(per_object) < 5.3
