"""Calibration of the stated pair uncertainty over many simulated pairs (forest types, distances,
headings): the fraction of pairs whose true error is within 1x, 2x and 3x the stated 1-sigma."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.tls.pair import register
from forestreg.engine.tls.params import RegistrationParams

PLOTS = (
    ("mixed_temperate", ((0.0, 0.0), (8.0, 3.0), (-4.0, 9.0)), 41),
    ("planted_conifer", ((0.0, 0.0), (-7.0, 5.0), (6.0, -9.0)), 42),
    ("mixed_temperate", ((0.0, 0.0), (12.0, -2.0), (3.0, 11.0)), 43),
    ("planted_conifer", ((0.0, 0.0), (10.0, 6.0), (-9.0, -6.0)), 44),
)


@pytest.mark.slow
def test_stated_uncertainty_is_calibrated_over_many_pairs(sim_plot):
    ratios, failed = [], 0
    for preset, positions, seed in PLOTS:
        plot = sim_plot(preset, positions, seed=seed, step=0.3, size=45.0)
        for i in range(len(positions)):
            for j in range(i + 1, len(positions)):
                result = register(plot.scans[i].scan, plot.scans[j].scan, RegistrationParams(angular_step_deg=0.3))
                if not result.ok:
                    failed += 1
                    continue
                truth = plot.relative_pose(i, j)
                rot, _ = rigid_errors(result.matrix, truth)
                trans = float(np.linalg.norm((result.matrix - truth)[:3, 3]))  # at the moving scanner (its origin)
                u = result.uncertainty
                assert u and u["translation_m"] > 0 and u["rotation_deg"] > 0
                ratios.append(max(trans / u["translation_m"], rot / u["rotation_deg"]))
    ratios = np.array(ratios)
    within = {k: float(np.mean(ratios <= k)) for k in (1, 2, 3)}
    print(
        f"calibration over {len(ratios)} pairs ({failed} failed honestly): within 1x {within[1]:.2f}, 2x {within[2]:.2f}, 3x {within[3]:.2f}; median ratio {np.median(ratios):.2f}"
    )
    assert len(ratios) >= 8
    assert within[3] >= 0.9, "the true error exceeds 3x the stated uncertainty too often"
    assert np.median(ratios) > 0.02, "the stated uncertainty is uselessly large"
