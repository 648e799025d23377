"""Progress display for long prepasses and renders (tqdm on a terminal, silent otherwise)."""
import os

from tqdm.auto import tqdm


def progress(total=None, desc="", unit="it", show=True):
    """A tqdm bar on stderr; hidden when stderr is not a terminal, MI_TWOPASS_QUIET is set or
    ``show`` is false (a caller's ``progress=False``): a hidden bar's ``update`` does nothing,
    so callers use it either way."""
    disable = True if (not show or os.environ.get("MI_TWOPASS_QUIET")) else None
    return tqdm(total=total, desc=desc, unit=unit, disable=disable, leave=False, dynamic_ncols=True)
