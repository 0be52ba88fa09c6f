"""Trivial userspace HAL probe for LinuxCNC tests: `out` is true while `z` <= `threshold`.

Loaded by start_linuxcnc.sh --probe-comp with Debian's /usr/bin/python3 (the `hal` module is
built for it, not for a venv or pyenv Python):
    loadusr -Wn rumba-probe /usr/bin/python3 probe_comp.py
    net rumba-probe-trip rumba-probe.out => motion.probe-input
    net probe-z joint.2.pos-fb => rumba-probe.z          (a --halcmd line)
A "surface" at joint Z = threshold (default -2 mm); polled every ~0.2 ms, so against a 1 ms
servo thread G38.2 at F100 overshoots by ~2 um.
"""

import time

import hal

comp = hal.component("rumba-probe")
comp.newpin("z", hal.HAL_FLOAT, hal.HAL_IN)
comp.newpin("threshold", hal.HAL_FLOAT, hal.HAL_IN)
comp.newpin("out", hal.HAL_BIT, hal.HAL_OUT)
comp["threshold"] = -2.0
comp.ready()
try:
    while True:
        comp["out"] = comp["z"] <= comp["threshold"]
        time.sleep(0.0002)
except KeyboardInterrupt:
    pass
