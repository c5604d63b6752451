"""Where the tests' real files are: `tests/data/` (what each file is, its source and licence:
`tests/data/README.md`). Every test that reads them takes the paths from here."""

from pathlib import Path

DATA = Path(__file__).resolve().parent / "data"
CITYGML = DATA / "citygml"
CITYJSON = DATA / "cityjson"
LUND = DATA / "images" / "lund"
