"""Where the tests find the repository's real example (one definition for every test file).

The excerpt of the 2022-11-10 deployment ships with the repository under
``examples/rts_20221110/data`` (provenance and licence notices in its ``SOURCE.md``), so the
tests that use it never skip.
"""

from pathlib import Path

#: Root of the checkout.
REPO = Path(__file__).resolve().parents[1]
#: The real example: ``deployment.toml`` and its ``data/`` folder.
EXAMPLE_DIR = REPO / "examples" / "rts_20221110"
#: The example's deployment file (paths inside are relative to it).
EXAMPLE_TOML = EXAMPLE_DIR / "deployment.toml"
#: The real excerpt's files (``prism1.csv``, ``GCP.txt``, ``static/``, ...).
EXCERPT = EXAMPLE_DIR / "data"
