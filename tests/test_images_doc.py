"""docs/images.md and docs/make_images.py: the generated blocks are filled and match the code's schema."""

from __future__ import annotations

import re
from pathlib import Path

from doc_scripts import load_doc_script

from stereopose_mc.sim import tracks_file
from stereopose_mc.sim.tracker import audit, klt

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "images.md"


def _block(text: str, name: str) -> str:
    return text.split(f"<!-- {name}:begin -->", 1)[1].split(f"<!-- {name}:end -->", 1)[0].strip()


def test_schema_tables_list_exactly_the_columns_the_code_writes():
    text = DOC.read_text(encoding="utf-8")
    for name, cols in (("tracks-schema", klt.COLUMNS), ("audit-schema", audit.AUDIT_COLUMNS),
                       ("tracks-file-schema", tracks_file.TRACK_FILE_COLUMNS),
                       ("truth-file-schema", tracks_file.TRUTH_FILE_COLUMNS)):  # fmt: skip
        listed = re.findall(r"^\| `(\w+)` \|", _block(text, name), flags=re.MULTILINE)
        assert listed == list(cols), name
    mi = load_doc_script("make_images")
    assert mi.schema_table({"a": "int64: one", "b": "float64"}).splitlines()[2:] == ["| `a` | int64 | one |",
                                                                                 "| `b` | float64 |  |"]


def test_detector_table_and_frames_are_generated():
    text = DOC.read_text(encoding="utf-8")
    table = _block(text, "detectors")
    for det in klt.DETECTORS:
        assert len(re.findall(rf"^\| [^|]+ \| {det} \|", table, flags=re.MULTILINE)) == 2, det  # both geometries
    frames = re.findall(r"\]\((images/[\w.-]+\.png)\)", _block(text, "frames"))
    assert len(frames) == 4 and all((ROOT / "docs" / f).is_file() for f in frames)
    assert _block(text, "run").startswith("Last run:")
