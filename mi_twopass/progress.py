"""Progress display for long prepasses and renders (tqdm on a terminal, silent otherwise)."""
import os

from tqdm.auto import tqdm


def progress(total=None, desc="", unit="it"):
    """A tqdm bar on stderr; hidden when stderr is not a terminal or MI_TWOPASS_QUIET is set."""
    disable = True if os.environ.get("MI_TWOPASS_QUIET") else None
    return tqdm(total=total, desc=desc, unit=unit, disable=disable, leave=False, dynamic_ncols=True)
