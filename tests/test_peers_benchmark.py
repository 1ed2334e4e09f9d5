"""benchmarks/peers.py without Mitsuba: diffshade's figures, one line, exit status 0; its
camera check (mask IoU) against a count by hand; and its table's ratios per round against
ratios worked out by hand."""

import json
import os
import subprocess
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

from peers import camera_check, table  # noqa: E402


def broken_mitsuba_env(tmp_path):
    """The environment of a benchmark run whose `mitsuba` fails to import as a broken
    install does (no libLLVM), ahead of any installed one: the run must not depend on which
    venv runs the tests."""
    fake = tmp_path / "fake" / "mitsuba"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('libLLVM not found (simulated)')\n")
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path / "fake"), ROOT]))


def test_without_mitsuba_prints_diffshade_figures_and_exits_cleanly(tmp_path):
    env = broken_mitsuba_env(tmp_path)
    out = tmp_path / "peers.json"
    done = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "peers.py"),
                           "--size", "32", "--subdivisions", "1", "--repeats", "1",
                           "--only", "hard_forward", "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.splitlines()
    said = [line for line in lines if line.startswith("Mitsuba 3 did not run")]
    assert len(said) == 1 and "libLLVM not found (simulated)" in said[0], done.stdout
    row = [line for line in lines if line.startswith("| hard forward |")]
    assert len(row) == 1 and row[0].endswith("| — | — |"), done.stdout
    result = json.loads(out.read_text())
    assert result["mitsuba"] is None
    assert set(result["diffshade"]) == {"hard_forward"}
    assert result["diffshade"]["hard_forward"]["median_s"] > 0


def test_camera_check_iou_and_interior_difference():
    # two 10 x 10 squares overlapping in a 10 x 6 band: IoU = 60 / 140
    ours, theirs = np.zeros((20, 24, 4)), np.zeros((20, 24, 4))
    ours[5:15, 2:12] = (0.5, 0.5, 0.5, 1.0)
    theirs[5:15, 6:16] = (0.5, 0.5, 0.5, 0.75)
    theirs[10, 9, 1] = 0.8     # inside both masks, 2 pixels from their common outline
    theirs[5, 8, 0] = 0.9      # on the outline: not compared
    iou, max_diff = camera_check(ours, theirs)
    assert np.isclose(iou, 60 / 140)
    assert np.isclose(max_diff, 0.3)


def test_table_pairs_each_round_of_the_two_engines():
    # round i of diffshade against round i of Mitsuba: 16 / 8, 15 / 6 and 14 / 7, so
    # 2.00-2.50x; rounds paired in sorted order instead (16 / 8, 15 / 7, 14 / 6) would
    # give 2.00-2.33x
    ours = {"soft_forward": {"median_s": 0.007, "round_medians_s": [0.008, 0.006, 0.007]},
            "soft_fb_material_vertices": {"median_s": 0.02, "round_medians_s": [0.02]}}
    theirs = {"forward": {"median_s": 0.015, "round_medians_s": [0.016, 0.015, 0.014]},
              "forward_backward": {"median_s": 0.04, "round_medians_s": [0.04, 0.04, 0.04]}}
    rows = {line.split(" | ")[0]: line for line in table(ours, theirs).splitlines()}
    assert rows["| soft forward"] == "| soft forward | 7.0 ms | 15.0 ms | 2.14x | 2.00–2.50x |"
    # no Mitsuba counterpart: no ratio either way
    assert rows["| soft f+b, material + vertices"].endswith("| — | — | — |")
