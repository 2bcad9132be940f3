"""Where the tests find ../shared/realdata (real instrument and vendor files; never copied into the repository)."""
import os
from pathlib import Path


def realdata_root() -> Path:
    """``MARKCAL_REALDATA`` when set, else the folder beside the repository, else /work/shared/realdata (which may be
    absent: the tests then skip with a reason)."""
    env = os.environ.get("MARKCAL_REALDATA")
    if env:
        return Path(env)
    beside = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata"
    return beside if beside.is_dir() else Path("/work/shared/realdata")
