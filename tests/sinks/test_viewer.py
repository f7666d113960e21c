"""The real Rerun viewer opens a recording the monitor wrote and draws its default views.

`rerun --headless` runs the viewer offscreen (software Vulkan, Mesa's lavapipe, from the
system packages); `ViewerClient.save_screenshot` asks it for a picture once it has loaded.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from monitor.bus.codec import load_database
from monitor.pipeline import MonitorConfig, MonitorPipeline
from monitor.sinks.rerun import RerunSink
from sim_ecu.ecu import VirtualECU
from sim_ecu.scenario import load_scenario
from tests.support import BIN
from tests.support.pipeline import feed_all

RERUN = str(BIN / "rerun")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.skipif(not Path("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json").exists()
                    and not os.environ.get("CI"),
                    reason="needs Mesa's software Vulkan (mesa-vulkan-drivers)")
def test_viewer_renders_the_recording(tmp_path: Path) -> None:
    from rerun.experimental import ViewerClient

    rrd = tmp_path / "run.rrd"
    db = load_database()
    sink = RerunSink(rrd_path=rrd, nodes=(0,))
    pipe = MonitorPipeline(db, MonitorConfig(nodes=(0,)), sink=sink)
    ecu = VirtualECU(None, db, 0, load_scenario("fault-outage-recovery"), seed=1)
    feed_all(pipe, ecu.frames(start_time=1.7e9))
    sink.close()
    port = _free_port()
    env = dict(os.environ, CI="1")  # no analytics from the viewer
    viewer = subprocess.Popen(
        [RERUN, "--headless", "--window-size", "1200x800", "--port", str(port), str(rrd)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True,
    )
    shot = tmp_path / "viewer.png"
    try:
        deadline = time.monotonic() + 90
        client = None
        while client is None:
            try:
                client = ViewerClient(f"rerun+http://127.0.0.1:{port}/proxy")
            except Exception:
                if time.monotonic() > deadline or viewer.poll() is not None:
                    raise
                time.sleep(0.5)
        time.sleep(5)  # let the viewer load the whole file before it paints
        entities = {e.entity_path for e in client.get_recording_schema(paths_only=True).entities}
        blueprint = str(client.get_blueprint().blueprint)
        client.save_screenshot(str(shot))
    finally:
        os.killpg(viewer.pid, signal.SIGTERM)
        viewer.wait(timeout=30)
    # the viewer holds what the monitor logged, laid out by our default blueprint
    for path in ("/node/0/ArmatureCurrent/measured", "/node/0/ArmatureCurrent/estimated",
                 "/node/0/gamma/estimate", "/node/0/gamma/sd", "/node/0/gamma/F1",
                 "/node/0/gamma/true", "/node/0/health", "/node/0/rules", "/node/0/events",
                 "/node/0/ArmatureCurrent/noise", "/node/0/process_noise",
                 "/monitor/counters/samples/estimated"):
        assert path in entities, (path, sorted(entities))
    for name in ("node 0", "daemon"):
        assert f"'display_name': '{name}'" in blueprint, blueprint[:500]
    # the noise factors' view, showing the two series its query names (its name holds a
    # quote, so the blueprint's repr puts it in double quotes)
    assert "'display_name': \"noise factors (1: the model's)\"" in blueprint
    assert "'query': ['$origin/ArmatureCurrent/noise', '$origin/process_noise']" in blueprint
    import matplotlib.image

    img = matplotlib.image.imread(shot)
    assert img.shape[0] >= 800 and img.shape[1] >= 1200
    # a drawn UI with plots, not a blank frame: many distinct colours
    colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 200
