"""Figures for the SR4000 emulator: xyz error vs truth per range band on 3 seeded scenes, the share
of low-confidence pixels, and the time per frame beside the bare render.

    .venv/bin/python tests/bench/measure_tof.py
"""
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(REPO), str(REPO / "tests" / "drivers")]
from test_sr4000 import UNFILTERED, mast_pose, range_errors  # noqa: E402

from drivers.sim.clock import SimClock  # noqa: E402
from drivers.sim.render import render  # noqa: E402
from drivers.sim.world import World, WorldConfig  # noqa: E402
from drivers.sr4000 import CONFIDENCE_FULL, Sr4000Settings, grab, preview, wait_for_exposure  # noqa: E402
from drivers.sr4000_emulator import MRPT_INTRINSICS, Exposure, Sr4000Emulator, simulate_frame  # noqa: E402

BANDS = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 99)]
HALF = CONFIDENCE_FULL // 2


def stats(err, true, mask):
    rows = []
    for lo, hi in BANDS:
        b = mask & (true >= lo) & (true < hi)
        if b.sum() == 0:
            rows.append(f"  {lo}-{hi if hi < 99 else ''} m: n=0")
            continue
        e = err[b]
        rows.append(f"  {lo}-{hi if hi < 99 else ''} m: n={b.sum():5d} mean={e.mean()*1000:+8.1f} mm  "
                    f"RMSE={np.sqrt(np.mean(e**2))*1000:8.1f} mm  p95|e|={np.percentile(np.abs(e), 95)*1000:8.1f} mm")
    return rows


def run(label, frames_of_scene):
    errs, trues, masks, confs = [], [], [], []
    for cam, frame in frames_of_scene:
        e = range_errors(cam, frame)
        hit = cam.last_view.hit & (frame.distance > 0)
        errs.append(e["point_error"] * np.sign(e["error"]))
        trues.append(e["true"])
        masks.append(hit)
        confs.append(hit & (frame.confidence >= HALF))
    err, true, mask, conf = (np.concatenate([a.ravel() for a in x]) for x in (errs, trues, masks, confs))
    print(f"\n{label}: all measured pixels (signed 3D error of emulated point vs ray hit)")
    print("\n".join(stats(err, true, mask)))
    print(f"{label}: confident pixels (confidence >= 50%)")
    print("\n".join(stats(err, true, conf)))
    low = mask & ~conf
    print(f"  low-confidence share: {low.sum()/mask.sum():.1%} overall; per band " + ", ".join(
        f"{lo}-{hi if hi < 99 else ''}: "
        f"{(low & (true >= lo) & (true < hi)).sum() / max(1, (mask & (true >= lo) & (true < hi)).sum()):.0%}"
        for lo, hi in BANDS[1:]))


scenes = []
for seed, heading in ((1, 0.0), (2, 120.0), (3, 240.0)):
    t = time.time()
    w = World.build(WorldConfig(seed=seed, size_m=(20.0, 20.0)))
    pose = mast_pose(w, 0.0, 0.0, heading, 35.0, 1.5)
    scenes.append((seed, w, pose))
    print(f"scene seed {seed}: built in {time.time()-t:.1f} s, {len(w.rocks)} rocks")


def make(w, pose, seed, **kw):
    return Sr4000Emulator(w, lambda: pose, SimClock(1e4), seed=seed, settings=Sr4000Settings.checked(**kw)).open()


single, unfiltered, averaged, settle = [], [], [], []
for seed, w, pose in scenes:
    cam = make(w, pose, seed)
    ok, used = wait_for_exposure(cam, 10)
    settle.append((ok, used, cam.integration_time()))
    single.append((cam, cam.acquire()))
    cam2 = make(w, pose, seed)
    cam2.set_mode(UNFILTERED)
    wait_for_exposure(cam2, 10)
    unfiltered.append((cam2, cam2.acquire()))
    cam3 = make(w, pose, seed)
    r = grab(cam3, frames=10, min_confidence=0, settle_frames=10)
    averaged.append((cam3, r.frame))
print("\nauto exposure (settled, frames, register):", settle)
run("DEFAULT MODE (FIX_PTRN|CONV_GRAY|DENOISE_ANF|CONF_MAP), single frame", single)
run("UNFILTERED (FIX_PTRN|CONF_MAP), single frame", unfiltered)
run("DEFAULT MODE, grab() of 10 frames", averaged)

# timing
cam, _ = single[0]
w, pose = scenes[0][1], scenes[0][2]
ex = Exposure(cam.integration_time(), cam.modulation_frequency(), cam.mode(), 0)
rng = np.random.default_rng(0)
tr, ts, ta = [], [], []
for _ in range(60):
    t0 = time.perf_counter()
    v = render(w, pose, MRPT_INTRINSICS, shadows=False)
    _ = v.range, v.albedo, v.incidence_cos   # the three images, computed on first read
    t1 = time.perf_counter()
    simulate_frame(v, cam._directions, ex, cam.model, rng, cam._edge_positions)
    t2 = time.perf_counter()
    cam.acquire()
    t3 = time.perf_counter()
    tr.append(t1 - t0)
    ts.append(t2 - t1)
    ta.append(t3 - t2)


def med(x):
    return np.median(x[10:]) * 1000


print(f"\nms per frame (median of 50): bare render + the 3 images read {med(tr):.2f}, sensor model {med(ts):.2f}, "
      f"whole acquire() {med(ta):.2f}")

# pictures of one view
cam, frame = single[0]


def big(rgb):
    return cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), (176*3, 144*3), interpolation=cv2.INTER_NEAREST)


cv2.imwrite("/tmp/rvs-tof-pictures/distance.png", big(preview(frame, "distance")))
cv2.imwrite("/tmp/rvs-tof-pictures/amplitude.png", big(preview(frame, "amplitude")))
cv2.imwrite("/tmp/rvs-tof-pictures/confidence.png", big(preview(frame, "confidence")))
print("saved /tmp/rvs-tof-pictures/{distance,amplitude,confidence}.png, integration", frame.integration_time)
for cam, fr in averaged:
    e = range_errors(cam, fr)
    b = (e["true"] >= 4) & (e["true"] < 5) & (fr.distance > 0)
    far = b & (np.abs(e["error"]) > 1)
    print("4-5 m band, |error| > 1 m:", far.sum(), "of", b.sum(),
          "true ranges", np.round(np.sort(e["true"][far])[:5], 3),
          "flying", (cam.last_images.flying_m[far] > 0.05).sum())
