"""Read a Q-DAS (AQDEF) file with aqdefreader, an independent reader, and print what it read.

Run by the tests with the aqdefreader peer's own interpreter (.peers/aqdef/bin/python, see
.ci/install-peers.sh): ``python aqdef_read.py FILE.dfq`` prints one JSON object
``{K2001 name: {"K2110": lower, "K2111": upper, "values": [K0001 …]}}`` for part 0.
"""

import contextlib
import json
import sys

import aqdefreader

with contextlib.redirect_stdout(sys.stderr):  # the reader reports its encoding guess on stdout
    part = aqdefreader.read_dfq_file(sys.argv[1]).get_part(0)
out = {}
for c in part.get_characteristics():
    out[c.get_data("K2001")] = {
        "K2110": c.get_data("K2110"), "K2111": c.get_data("K2111"),
        "values": [float(m.value) for m in c.get_measurements()]}
print(json.dumps(out))
