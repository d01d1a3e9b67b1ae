"""The person model each sensor judges by: the stereo pair's legs read wider against a torso whose
arms it loses beyond 6 m, so its legs-to-torso limit sits higher than the SR4000's."""
from __future__ import annotations

import pytest

from rvs_server.tracking.settings import TrackingSettings


def test_a_stereo_walker_whose_legs_read_096_of_its_torso_is_a_person_and_a_boulder_at_105_is_not():
    settings = TrackingSettings()
    stereo, tof = settings.person("stereo"), settings.person("tof")
    assert stereo.legs_to_torso(0.96) > 0.3 and tof.legs_to_torso(0.96) < 0.3
    for model in (stereo, tof):
        assert model.legs_to_torso(1.05) == 0.0        # widest at its foot: a boulder
        assert model.legs_to_torso(0.8) == 1.0
    assert settings.standing("tof").noise_per_m2 == 0.0 and settings.standing("stereo").noise_per_m2 > 0.0


def test_a_stereo_centre_is_sure_across_the_line_of_sight_and_unsure_along_it_and_a_tof_one_alike():
    import numpy as np
    settings = TrackingSettings()
    offset = np.array([0.0, 6.0])                      # 6 m out along world y
    stereo = settings.measurement_cov("stereo", offset)
    along = settings.stereo_sigma_m + settings.stereo_sigma_per_m2 * 36.0
    assert np.allclose(stereo, np.diag([settings.stereo_across_sigma_m ** 2, along ** 2]))
    assert np.allclose(settings.measurement_cov("tof", offset), np.eye(2) * settings.tof_sigma_m ** 2)
    turned = settings.measurement_cov("stereo", np.array([6.0, 6.0]) / np.sqrt(2))
    assert np.allclose(turned, turned.T) and np.linalg.eigvalsh(turned) == pytest.approx(sorted(np.diag(stereo)))
