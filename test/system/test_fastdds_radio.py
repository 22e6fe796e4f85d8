"""config/fastdds_radio.xml: the profile for a mapper whose merger listens over a radio link. Its
per-topic writer profiles name the mapper's topics that cross the link, and Fast DDS builds paced
writers from it: a 1 MB message takes as long as the flow controller's rate says, not milliseconds."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytest.importorskip("rclpy", reason="the ROS extra is not installed")

pytestmark = [pytest.mark.ros]

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "config" / "fastdds_radio.xml"
NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def _paced_topics() -> set[str]:
    root = ET.parse(PROFILE).getroot()
    return {w.get("profile_name", "") for w in root.iter(f"{NS}data_writer")
            if w.findtext(f"{NS}qos/{NS}publishMode/{NS}flow_controller_name") == "memgs_radio"}


def test_the_paced_topics_are_the_mappers_link_topics() -> None:
    source = (ROOT / "memgs_ros" / "nodes" / "mapper" / "outputs.py").read_text()  # the mapper's publishers
    published = set(re.findall(r'create_publisher\(\w+, "(memgs/(?:map/delta|mapper/snapshot|render/\w+))"', source))
    assert published == {"memgs/map/delta", "memgs/mapper/snapshot", "memgs/render/color", "memgs/render/depth",
                         "memgs/render/camera_info"}
    assert _paced_topics() == {"/" + t for t in published}


SUBSCRIBE = """
import sys, time, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt8MultiArray
rclpy.init()
node = rclpy.create_node("radio_profile_reader")
got = []
node.create_subscription(UInt8MultiArray, "/memgs/map/delta", got.append,
                         QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
end = time.monotonic() + 40
while not got and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
print(len(got[0].data) if got else -1)
"""

PUBLISH = """
import time, rclpy
from rclpy.duration import Duration
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt8MultiArray
rclpy.init()
node = rclpy.create_node("radio_profile_writer")
pub = node.create_publisher(UInt8MultiArray, "/memgs/map/delta",
                            QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
end = time.monotonic() + 30
while pub.get_subscription_count() == 0 and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
msg = UInt8MultiArray()
msg.data = bytes(1_000_000)
t0 = time.monotonic()
pub.publish(msg)
acked = pub.wait_for_all_acked(Duration(seconds=30))
print(acked, time.monotonic() - t0)
"""


def test_fast_dds_paces_a_writer_by_the_radio_profile(ros_domain_id: int) -> None:
    root = ET.parse(PROFILE).getroot()
    fc = next(root.iter(f"{NS}flow_controller_descriptor"))
    rate = int(fc.findtext(f"{NS}max_bytes_per_period")) / int(fc.findtext(f"{NS}period_ms")) * 1e3  # bytes/s
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), FASTRTPS_DEFAULT_PROFILES_FILE=str(PROFILE),
               FASTDDS_DEFAULT_PROFILES_FILE=str(PROFILE), RMW_FASTRTPS_PUBLICATION_MODE="ASYNCHRONOUS")
    # Reader and writer in two processes, as mapper and merger: within one participant Fast DDS
    # hands a message over directly, past the flow controller.
    reader = subprocess.Popen([sys.executable, "-c", SUBSCRIBE], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        out = subprocess.run([sys.executable, "-c", PUBLISH], env=env, capture_output=True, text=True, timeout=90)
        got, err = reader.communicate(timeout=60)
    finally:
        if reader.poll() is None:
            reader.kill()
    assert out.returncode == 0, out.stderr[-2000:]
    assert got.split()[-1] == "1000000", err[-2000:]
    acked, took = out.stdout.split()[-2] == "True", float(out.stdout.split()[-1])
    assert acked, out.stderr[-2000:]
    # 1 MB at 562.5 kB/s: 1.78 s (the first period's bytes go at once); unpaced, milliseconds.
    assert 0.7 * 1e6 / rate < took < 1e6 / rate + 5.0, (took, out.stderr[-2000:])
