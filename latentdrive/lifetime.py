"""The lifetime of the processes latentdrive starts: they end with the process that started them.

A parent stopped by Ctrl-C or a terminate stops its children itself; one killed outright
(``kill -9``, the out-of-memory killer) cannot, and its children would run on, orphaned,
writing into a folder no one waits on. Every process latentdrive starts through
``multiprocessing`` (the study's steps, the BNN study's runs, the search's workers, data
collection's pool) calls :func:`die_with_parent` first.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
from multiprocessing.connection import wait as mp_wait

__all__ = ["die_with_parent"]


def die_with_parent() -> None:
    """Have this multiprocessing child terminated as soon as the process that started it ends.

    A daemon thread waits on the parent's sentinel and sends this process SIGTERM when it
    fires. The sentinel, not the kernel's parent-death signal: under the forkserver the OS
    parent is the server, which outlives the process that asked for the child while any
    child lives. Does nothing outside a multiprocessing child.
    """
    parent = mp.parent_process()
    if parent is None:
        return

    def watch() -> None:
        mp_wait([parent.sentinel])
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="latentdrive parent watch", daemon=True).start()
