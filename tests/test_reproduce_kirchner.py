"""scripts/reproduce_kirchner.py: one --quick run; figures, FIM vs random, bounds, cooperation.

Example 1 is the paper's stationary target (position only, d = 2); its moving-target variant
(d = 6) is run alongside for comparison (see docs/REPRODUCTION.md).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("kirchner_figures")
    results = load_script("reproduce_kirchner").main(["--quick", "--out", str(out)])
    return out, results


def test_four_figures_written(run):
    out, results = run
    for name in ("kirchner_fig3", "kirchner_fig5", "kirchner_fig7", "kirchner_geometry"):
        path = out / f"{name}.png"
        assert path.is_file() and path.stat().st_size > 10_000, path
        assert results["figures"][name] == str(path)


def test_quick_run_config(run):
    _, results = run
    cfg = results["config"]
    assert cfg["quick"] and cfg["trials"] >= 8
    for ex in ("example1", "example2", "example3", "example1_moving"):
        for s in results[ex]["methods"].values():
            assert s["errors"].shape == (cfg["trials"], len(cfg["ks"]))
            assert np.all(np.isfinite(s["errors"]))


def test_fim_beats_random_at_smallest_k(run):
    _, results = run
    # example 2 (camera + Doppler): MAP position error
    m = results["example2"]["methods"]
    assert m["fim"]["mean"][0] < m["random"]["mean"][0]
    # example 1 (stationary target, the paper's setting): MAP error and bound
    m = results["example1"]["methods"]
    assert m["fim"]["mean"][0] < m["random"]["mean"][0]
    assert m["fim"]["crlb"][0] < m["random"]["crlb"][0]


def test_fim_crlb_non_increasing_in_k(run):
    _, results = run
    curves = [results[ex]["methods"]["fim"]["crlb"] for ex in ("example1", "example2")]
    curves += [results["example3"]["methods"][n]["crlb"] for n in ("independent", "cooperative")]
    for crlb in curves:
        assert np.all(np.diff(crlb) <= 1e-9 * crlb[:-1])


def test_cooperative_bound_at_least_as_good_as_independent(run):
    _, results = run
    m = results["example3"]["methods"]
    # CRLB volume: f(S) = log det FIM(S) - log det Q0 = log det(P0) - log det(CRLB(S))
    assert np.all(m["cooperative"]["logdet"] >= m["independent"]["logdet"] - 1e-9)
    # two agents (2K picks) bound the position better than either agent alone (K picks)
    for name in ("independent", "cooperative"):
        for alone in ("agent1", "agent2"):
            assert np.all(m[name]["crlb"] <= m[alone]["crlb"] + 1e-9)


def test_sensor_mix_is_mixed(run):
    _, results = run
    mix = results["example2_sensor_mix"]
    assert np.all(mix["n_camera"] + mix["n_doppler"] == mix["ks"])
    k10 = 9  # K = 10
    assert 0 < mix["n_doppler"][k10] < mix["n_camera"][k10]
