"""``archer emulate realsense --twin``: the twin's frames through librealsense and the camera service, in real time."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np

from onboard.contracts.binary_messages import decode_color, decode_depth
from onboard.contracts.topics import TOPICS
from services.runtime.zenoh_session import open_session

NS_KEY = "archer/test-emulate-realsense"


def test_emulated_d435_publishes_the_twins_depth_and_colour(zenoh_router, tmp_path) -> None:
    config = tmp_path / "camera.toml"
    config.write_text('[camera]\nwidth = 424\nheight = 240\nfps = 15\ncolor_width = 424\ncolor_height = 240\n'
                      'color_fps = 15\ndecimation = 2\ncapture = "every"\nstate_max_age_s = 1.0\n')
    client = open_session(zenoh_router, "peer")
    depths, colors = [], []
    subs = [client.declare_subscriber(TOPICS["depth"].key(NS_KEY), lambda s: depths.append(decode_depth(s.payload.to_bytes()))),
            client.declare_subscriber(TOPICS["color"].key(NS_KEY), lambda s: colors.append(decode_color(s.payload.to_bytes())))]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "emulate", "realsense", "--twin", "hop-in-place",
                             "--config", str(config), "--endpoint", zenoh_router, "--namespace", NS_KEY, "--truth-pose"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        info = json.loads(proc.stdout.readline())
        assert info["device"] == "realsense" and info["mode"] == "424x240@15" and info["truth_pose"]
        end = time.monotonic() + 60.0
        while (len(depths) < 3 or len(colors) < 3) and time.monotonic() < end and proc.poll() is None:
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            proc.terminate()
        out, err = proc.communicate(timeout=30)
        for s in subs:
            s.undeclare()
        client.close()
    assert proc.returncode == 0, err
    final = json.loads(err.strip().splitlines()[-1])["final"]
    assert len(depths) >= 3 and len(colors) >= 3, final
    img, rgb = depths[-1], colors[-1]
    assert img.depth.shape == (120, 212) and rgb.rgb.shape == (120, 212, 3)  # decimated by the SDK
    ret = img.depth > 0
    assert ret.mean() > 0.5 and 0.3 < float(np.median(img.depth[ret])) < 3.0  # the floor ahead, below the camera
    assert 0.4 < img.cam_pos[2] < 1.0 and final["renders"] >= 3 and final["published"] >= 3
    assert rgb.stamp_ns == img.stamp_ns and rgb.rgb[ret].mean() > 30  # lit floor, not black
