"""benchmarks/sfm.py's pose errors and table on known cameras (no pipeline run)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_benchmark

from sgpor_pipeline.orientation import Similarity
from sgpor_pipeline.scene import Camera
from sgpor_pipeline.synthetic import look_at


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("sfm")


def ring(n: int = 8, radius: float = 2.0) -> list[Camera]:
    K = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), 0.5])
        cams.append(Camera(f"v{i}", 128, 96, K, look_at(eye, np.zeros(3)), f"v{i}"))
    return cams


def test_pose_errors_ignore_a_similarity_and_find_a_moved_camera(bench):
    truth = ring()
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    sim = Similarity(0.3, R, np.array([1.0, -2.0, 0.5]))
    moved = [sim.camera(c) for c in truth]  # the same rig in another frame (SfM's gauge)
    e = bench.pose_errors(truth, moved)
    assert e["centre_err_max"] < 1e-9 and e["rot_err_max"] < 1e-4 and not e["wrong"]
    # one camera 0.5 m off (a quarter of the ring's radius) and turned 10 degrees: a wrong model
    c = truth[3]
    a = np.radians(10)
    turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    T = c.cam_from_world.copy()
    T[:3, :3] = turn @ T[:3, :3]
    T[:3, 3] = -T[:3, :3] @ (c.center + [0.0, 0.0, 0.5])
    bad = [*truth[:3], Camera(c.name, c.width, c.height, c.K, T, c.image), *truth[4:]]
    e = bench.pose_errors(truth, bad)
    assert e["wrong"] and e["rot_err_max"] == pytest.approx(10.0, abs=1.5) and 0.1 < e["centre_err_max"] < 0.4
    # unregistered views are left out; fewer than 3 shared cameras: no figure
    assert bench.pose_errors(truth, truth[:5])["centre_err_max"] < 1e-9
    assert bench.pose_errors(truth, truth[:2]) is None


def test_table_marks_wrong_models_and_repairs(bench):
    row = {"scene": "synthetic-inward0", "images": 24, "registered": 24, "unregistered": [], "seconds": 2.0,
           "cache_hit": False, "reprojection_error": 0.5, "points": 383, "steps": {"map": 0.5},
           "pose": {"centre_err_median": 0.009, "centre_err_max": 0.019, "rot_err_median": 0.7, "rot_err_max": 1.1,
                    "wrong": False},
           "contradicted": 0, "repaired": True}
    wrong = {**row, "scene": "synthetic-inward3", "repaired": False, "contradicted": 3,
             "pose": {**row["pose"], "centre_err_max": 9.8, "wrong": True}}
    table = bench.format_table([row, wrong, {"scene": "lund", "skipped": "not found"}])
    lines = table.splitlines()
    assert "0.9/1.9%" in lines[1] and "0 contra, rep" in lines[1] and " !" not in lines[1]
    assert "980.0%" in lines[2] and " !" in lines[2] and "3 contra" in lines[2]
    assert "lund" in lines[3] and "skipped" in lines[3]
