"""The person model each sensor judges by: the stereo pair's legs read wider against a torso whose
arms it loses beyond 6 m, so its legs-to-torso limit sits higher than the SR4000's."""
from __future__ import annotations

from rvs_server.tracking.settings import TrackingSettings


def test_a_stereo_walker_whose_legs_read_096_of_its_torso_is_a_person_and_a_boulder_at_105_is_not():
    settings = TrackingSettings()
    stereo, tof = settings.person("stereo"), settings.person("tof")
    assert stereo.legs_to_torso(0.96) > 0.3 and tof.legs_to_torso(0.96) < 0.3
    for model in (stereo, tof):
        assert model.legs_to_torso(1.05) == 0.0        # widest at its foot: a boulder
        assert model.legs_to_torso(0.8) == 1.0
    assert settings.standing("tof").noise_per_m2 == 0.0 and settings.standing("stereo").noise_per_m2 > 0.0
