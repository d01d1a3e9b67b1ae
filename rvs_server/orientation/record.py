"""orient's product: orient.json (the belief, the motion and its covariance, the keyframe, which
sources were fused), the look's picture (tracks or depth overlap), and the simulator's truth."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from rvs_server.products.rasters import write_png
from toolbox.colour import upscale, with_title
from toolbox.odometry.chain import PlanarBelief

from .look import Look
from .odometer import OrientFailed, Sighting


def _belief(belief: PlanarBelief | None) -> dict[str, Any] | None:
    if belief is None:
        return None
    pose = belief.pose
    sigma_xy, sigma_heading = belief.sigmas()
    return {"x": pose.x, "y": pose.y, "z": pose.z, "heading_deg": math.degrees(pose.heading),
            "roll_deg": math.degrees(pose.roll), "pitch_deg": math.degrees(pose.pitch),
            "covariance_xy_heading": belief.covariance.tolist(), "sigma_xy_m": sigma_xy,
            "sigma_heading_deg": math.degrees(sigma_heading),
            **({"heading_drift_deg_per_m": math.degrees(belief.drift),
                "sigma_drift_deg_per_m": math.degrees(math.sqrt(max(float(belief.covariance[3, 3]), 0.0)))}
               if belief.drifts else {})}


def _look(look: Look) -> dict[str, Any]:
    estimate = look.estimate
    return {"sensor": look.sensor, "pan_tilt_deg": list(look.pan_tilt_deg),
            "estimate_before": {"x": estimate.x, "y": estimate.y, "heading_deg": math.degrees(estimate.heading)},
            "inclinometer_deg": {"roll": math.degrees(look.roll), "pitch": math.degrees(look.pitch)},
            "sun_sensor": None if look.sun is None else {"body": look.sun.body.tolist(),
                                                          "world": look.sun.world.tolist(),
                                                          "sigma_deg": math.degrees(look.sun.sigma)}}


def _aim(aim: Any) -> dict[str, Any] | None:
    if aim is None:
        return None
    return {"pan_deg": aim.pan_deg, "tilt_deg": aim.tilt_deg, "pointed": aim.pointed,
            "expected_share": round(aim.share, 3), "along_heading_share": round(aim.along_share, 3)}


def write_outcome(product: Any, sighting: Sighting, applied: bool) -> None:
    look, outcome = sighting.look, sighting.outcome
    motion = outcome.motion
    fix = outcome.sun
    data = {"look": _look(look), "applied": applied, "keyframe": outcome.keyframe, "rekeyed": outcome.rekeyed,
            "keyframe_number": outcome.keyframe_number, "sources": outcome.sources,
            "belief": _belief(outcome.belief), "odometry_only": _belief(outcome.odometry),
            "previous": _belief(outcome.previous),
            "motion": None if motion is None else {
                "key_from_new": motion.key_from_new.tolist(),
                "covariance_rotvec_translation": motion.covariance.tolist(),
                "matches": motion.matches, "inliers": motion.inliers, "overlap": motion.overlap, "rms": motion.rms,
                "method": motion.method},
            "sun": None if fix is None else {"heading_deg": math.degrees(fix.heading),
                                             "sigma_deg": math.degrees(fix.sigma),
                                             "innovation_sigmas": fix.innovation_sigmas, "used": fix.used},
            "odometry_ms": 1000.0 * outcome.odometry_s, "aim": _aim(sighting.aim),
            "rekeyed_along_heading": sighting.home is not None}
    product.write_json("orient.json", data, "the rover's pose after this look, how it was measured and how sure it is")
    pointed = f", head at pan {look.pan_tilt_deg[0]:.0f}" if sighting.aim.pointed else ""
    if outcome.keyframe:
        title = f"keyframe {outcome.keyframe_number}"
    else:
        title = (f"from keyframe {outcome.keyframe_number}: {motion.inliers} of {motion.matches} agree, "
                 f"{'+'.join(outcome.sources)}{pointed}")
    _picture(product, outcome.picture, look.sensor, title)


def write_failure(product: Any, look: Look, failed: OrientFailed) -> None:
    product.write_json("orient.json", {"look": _look(look), "failed": {"reason": failed.failure.reason,
                                                                       "sentence": failed.failure.sentence},
                                       "keyframe_number": failed.keyframe_number, "aim": _aim(failed.aim)},
                       "why this look could not be matched against the keyframe (the pose estimate is unchanged)")
    _picture(product, failed.picture, look.sensor, f"failed against keyframe {failed.keyframe_number}: "
             f"{failed.failure.reason}")


LEGEND = {"stereo": "tracks from the keyframe: green explained by the motion, red not",
          "tof": "to the keyframe cloud: green near, red far, blue none"}


def _picture(product: Any, picture: np.ndarray | None, sensor: str, title: str) -> None:
    if picture is not None:   # the toolbox draws BGR; a TOF frame is enlarged to be read
        rgb = with_title(with_title(upscale(np.ascontiguousarray(picture[..., ::-1])), LEGEND[sensor]), title)
        write_png(product.add("look.png", "the look: the features tracked from the keyframe (stereo) or the depth "
                              "overlap (TOF), with what the colours say"), rgb)
