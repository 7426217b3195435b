"""Persona owns the output folders it writes, and no other.

A run writes ``metrics.json``, ``report.html``, videos and pictures into its workflow's ``output:``
folder, replacing what a run before it wrote there. A folder that already holds files Persona did not
write (a user's own ``report.html``) must not be overwritten in silence: :func:`claim` marks a folder as
Persona's (a ``.persona-output`` file, the first time a run writes there) and stops a run, before any
work, whose output folder holds files but no mark, unless ``force``. A folder a run of an earlier version
wrote (its ``metrics.json`` names the same store) is taken as Persona's. Files a user puts into a folder
already marked are theirs to keep apart.
"""

from __future__ import annotations

import contextlib
import json
import os

from . import storage
from .errors import PersonaError

#: the file that marks a folder as Persona's output
MARK = ".persona-output"


class OutputTaken(PersonaError, ValueError):
    """The output folder holds files Persona did not write."""


def _ours_before(folder: str, store: str) -> bool:
    """True when ``folder``'s ``metrics.json`` is one a run wrote for ``store`` (before folders were marked)."""
    with contextlib.suppress(OSError, ValueError, TypeError):
        metrics = json.loads(storage.read_text(storage.join(folder, "metrics.json")))
        return isinstance(metrics, dict) and "workflow" in metrics and str(metrics.get("store")) == str(store)
    return False


def claim(folder: str, store: str, *, force: bool = False) -> None:
    """Make ``folder`` the output folder of a run on ``store``: created and marked if it is new or empty,
    or already Persona's. Raises :class:`OutputTaken`, naming a few of its files, when it holds files but is
    not Persona's, unless ``force``."""
    folder = str(folder)
    mark = storage.join(folder, MARK)
    if storage.exists(mark):
        return
    found = [storage.name(e) for e in storage.entries_in(folder)] if storage.isdir(folder) else []
    if found and not force and not _ours_before(folder, store):
        shown = ", ".join(found[:5]) + (f" and {len(found) - 5} more" if len(found) > 5 else "")
        raise OutputTaken(f"the output folder {folder} holds files Persona did not write ({shown}); a run "
                          "replaces metrics.json, report.html, index.html and the videos and pictures it makes: "
                          "set output: to another folder, or run with --force to let it write there")
    if not storage.is_url(folder):
        os.makedirs(folder, exist_ok=True)
    with storage.open_file(mark, "w") as f:
        f.write("This folder is a Persona run's output: a run writes over what is in it.\n")
