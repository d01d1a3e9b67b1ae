"""configs/orient.toml: how orient looks, when it keeps its keyframe, what it fuses."""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from rvs_server.config import PerSensor, Settings

Sensor = Literal["stereo", "tof"]
Share = Annotated[float, Field(ge=0, le=1)]
Tilt = Annotated[float, Field(ge=-80, le=10)]
Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]


class OrientSettings(Settings):
    sensor: Sensor = Field("stereo", description="the sensor orient looks with unless --sensor says")
    tilt_deg: PerSensor[Tilt] = Field(PerSensor[Tilt](stereo=-20.0, tof=-30.0), description="per sensor, the tilt "
                                      "while orienting (pan 0: along the heading)")
    aim_share: PerSensor[Share] = Field(
        PerSensor[Share](stereo=0.3, tof=0.3), description="per sensor: when the look along the heading would see "
        "less than this share of the keyframe's points (dead reckoning's guess), the head is turned back to them")
    wide_search_after_deg: float = Field(10.0, ge=0, description="stereo: after a turn this large since the last "
                                         "look, a look that fails is matched again in a window as wide as the wheels' "
                                         "heading can be off (wheels_deg ...)")
    reach_turn_deg: float = Field(90.0, gt=0, le=180, description="the largest turn in place after which a pointed "
                                  "look is known to find the keyframe again; a refusal past any pointing advises "
                                  "looking at least this often")
    reach_drive_turn_deg: float = Field(45.0, gt=0, le=180, description="the largest turn that may be followed by up "
                                        "to reach_m forward before the next look (past it the camera stands too far "
                                        "round for the keyframe's ground to match, wherever it points)")
    reach_m: float = Field(1.5, gt=0, description="the longest drive after which a pointed look is known to find the "
                           "keyframe again")
    tof_frames: int = Field(1, ge=1, le=20, description="SR4000 frames averaged per look")
    rekey_overlap: PerSensor[Share] = Field(
        PerSensor[Share](stereo=0.35, tof=0.9), description="per sensor: the new look becomes the keyframe when less "
        "than this share of the keyframe was found again (the next step might lose it)")
    rekey_inliers: int = Field(150, ge=0, description="... or (stereo) fewer tracked points agree than this")
    max_keyframe_m: PerSensor[Positive] = Field(PerSensor[Positive](stereo=2.0, tof=0.3), description="per "
                                                "sensor: ... or the rover is farther than this from the keyframe")
    max_keyframe_deg: float = Field(25.0, gt=0, le=180, description="... or has turned this much from it")
    covariance_scale: float = Field(1.0, gt=0, description="the odometry's own covariance times this: what the "
                                    "campaign measured it to be over-confident by")
    heading_sigma_scale: PerSensor[Positive] = Field(
        PerSensor[Positive](stereo=2.5, tof=1.2), description="per sensor, the odometry's heading sigma of each "
        "motion times this: the orient campaign (20 traverses per sensor, unsplit turns) found stereo's heading "
        "errors 2.5 times and TOF's 1.2 times what the fit's covariance said (median |error| / sigma 1.69 and 0.80 "
        "against a Gaussian's 0.67); believed, the sun's heading could not pull a stereo chain 0.25 deg off back")
    heading_drift_deg_per_m: PerSensor[NonNegative] = Field(
        PerSensor[NonNegative](stereo=0.02, tof=0.0), description="per sensor, the prior sigma of the odometry's "
        "heading drift per metre driven, a state learnt against the sun (0: none). Stereo's heading errors run the "
        "same way for tens of metres (about 0.01 deg a look on the orient campaign), which a filter of independent "
        "motions mistakes for certainty")
    heading_drift_walk: PerSensor[NonNegative] = Field(
        PerSensor[NonNegative](stereo=0.0005, tof=0.0), description="per sensor, how much the drift may change, "
        "deg per metre per root metre driven")
    # How far dead reckoning may be off since the last look (about 5 sigma of the drive error):
    # a measured motion farther from it is refused as diverged.
    wheels_m: float = Field(0.05, ge=0, description="position: this much ...")
    wheels_per_m: float = Field(0.10, ge=0, description="... plus this share of the distance driven")
    wheels_deg: float = Field(3.0, ge=0, description="heading: this much ...")
    wheels_deg_per_deg: float = Field(0.10, ge=0, description="... plus this share of the turn ...")
    wheels_deg_per_m: float = Field(1.5, ge=0, description="... plus this many degrees per metre driven")
    turn_on_spot_m: float = Field(0.03, ge=0, description="TOF: a look the wheels put this close to the last one "
                                  "(a turn on the spot) that free ICP cannot match is registered over the "
                                  "rotation about the rover's centre alone")
    lost_sigma_m: float = Field(0.5, gt=0, description="position sigma added to a keyframe taken after a failed "
                                "look (dead reckoning carried the rover there)")
    lost_sigma_deg: float = Field(5.0, gt=0, description="heading sigma added to such a keyframe")
    sun: bool = Field(True, description="fuse the sun sensor's heading when the rover has one")
    sun_samples: int = Field(10, ge=1, le=1000, description="sun sensor readings averaged per look (the rover "
                             "stands still; their white noise falls as the root of their count, the bias stays)")
    sun_gate_sigmas: float = Field(5.0, gt=0, description="a sun heading this many sigmas off the odometry's is "
                                   "refused")
