#!/usr/bin/env python3
"""The structure check fails where it must (issue 37): run on tests/structure/fixtures/forbidden,
it must exit 1 and name the viewer's include of server/, the physics' <fstream>, the long
function and the table's row for a function that is not there."""
import os
import subprocess
import sys

here = os.path.dirname(os.path.abspath(__file__))
run = subprocess.run([sys.executable, os.path.join(here, "check_structure.py"),
                      os.path.join(here, "fixtures", "forbidden")],
                     capture_output=True, text=True)
out = run.stdout + run.stderr
expected = [
    'viewer/view.cc:3: includes "server/contact/tool.h": viewer may include only common/app',
    "server/models/model.cc:2: includes <fstream>, which server/models may not",
    "common/app/long.cc:2: function Long is 173 lines",
    "long-functions names Gone in common/app/gone.cc",
]
missing = [e for e in expected if e not in out]
if run.returncode != 1 or missing:
    print(out)
    print("fixture_test: exit %d (want 1); missing: %s" % (run.returncode, missing))
    sys.exit(1)
print("fixture_test: the check fails on every planted fault")
