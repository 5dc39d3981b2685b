"""io.results.portable_json: a benchmark's committed results carry no machine path."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from orchard_mapping.io.results import portable_json


def test_temporary_home_and_current_folders_are_named_not_spelt():
    tmp, home, here = Path(tempfile.gettempdir()), Path.home(), Path.cwd()
    doc = {"work": str(tmp / "bench" / "row0"), "cfg": str(home / ".cfg"), "out": str(here / "out"),
           "tmp": str(tmp), "other": "/opt/data/x", "n": 3}
    got = json.loads(portable_json(doc))
    assert got == {"work": "<tmp>/bench/row0", "cfg": "~/.cfg", "out": "./out", "tmp": "<tmp>",
                   "other": "/opt/data/x", "n": 3}
