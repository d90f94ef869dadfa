import os
from pathlib import Path

import pytest

_DATA = Path(os.environ.get("SQJAX_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def data_path(*parts) -> Path:
    """Path into the real test data (``../shared/data`` beside the clone, or $SQJAX_DATA); skips when absent."""
    p = _DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real test data not found at {p} (set SQJAX_DATA to the shared/data folder)")
    return p
