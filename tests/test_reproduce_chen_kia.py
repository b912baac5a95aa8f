"""scripts/reproduce_chen_kia.py --quick: Table III ordering and Fig. 8 consistency."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    module = load_script("reproduce_chen_kia")
    out = tmp_path_factory.mktemp("chen_kia")
    return out, module.main(["--quick", "--out", str(out), "--workers", "1"])


def test_figures_written(run) -> None:
    out, res = run
    for name in ("chen_kia_fig8.png", "chen_kia_rmse.png"):
        assert (out / name).stat().st_size > 10_000


def test_table_iii_ordering(run) -> None:
    _, res = run
    r = {m: v["rmse"] for m, v in res["results"].items()}
    for m in ("naive", "ci", "dmv", "pecmv"):
        assert np.all(r[m] < r["dead_reckoning"])  # CL and beacons beat dead reckoning
    assert r["pecmv"][1] <= r["dmv"][1]  # PECMV is less conservative than DMV (paper)


def test_fig8_consistency(run) -> None:
    _, res = run
    lo, hi = res["band"]
    nees = {m: v["mean_nees"] for m, v in res["results"].items()}
    assert nees["naive"].max() > hi  # ignoring the correlation is overconfident
    for m in ("ci", "dmv"):
        assert nees[m][1] < hi  # conservative: inside or below the band
    assert nees["pecmv"][1] < hi
