"""Property: whatever a dataset manifest has been changed into, opening and verifying the
dataset either works, reading only files inside the dataset, or fails with one
DatasetError line. Never another exception, never a file elsewhere."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from helpers import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from latentdrive.data.dataset import ShardDataset
from latentdrive.data.shards import MANIFEST, DatasetError

JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=8,
)
#: Names a manifest could give a shard: hostile ones among them.
NAMES = st.sampled_from(["/etc/passwd", "../x.npz", "a/../../x.npz", "", ".", "..", "sub/x.npz", "x\x00.npz"]) | st.text(max_size=20)


def _paths(obj: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every key path into a JSON document (the root excluded)."""
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    for key, value in items:
        yield (*prefix, key)
        yield from _paths(value, (*prefix, key))


def _apply(doc: Any, path: tuple[Any, ...], value: Any, delete: bool) -> None:
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value


def _check_opens_or_fails_cleanly(root: Path, manifest: Any) -> None:
    (root / MANIFEST).write_text(json.dumps(manifest))
    try:
        ds = ShardDataset(root, allow_incomplete=True)
        ds.verify()
    except DatasetError as exc:
        msg = str(exc)
        assert "\n" not in msg and msg.startswith(str(root)), msg
        return
    inside = root.resolve()
    for name in ds.shard_names:
        assert (root / name).resolve().is_relative_to(inside), name


def _workspace(collected: Path) -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        # Hard links: the shards are only read, and a link inside the folder stays inside it.
        shutil.copytree(collected, root, copy_function=os.link)
        (root / MANIFEST).unlink()
        yield root


@settings(max_examples=examples(60), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_one_change_to_a_manifest_is_survived(collected: Path, data: st.DataObject) -> None:
    manifest = json.loads((collected / MANIFEST).read_text())
    paths = list(_paths(manifest))
    # Half of the changes hit what the reader interprets (the fields of units and shards,
    # the top-level keys), not the env configs that make up most of the document.
    read = [p for p in paths if len(p) == 1 or (p[0] in ("units", "shards") and len(p) == 3)]
    path = data.draw(st.sampled_from(read) | st.sampled_from(paths), label="path")
    delete = data.draw(st.booleans(), label="delete")
    value = data.draw(JSON, label="value")
    _apply(manifest, path, value, delete)
    for root in _workspace(collected):
        _check_opens_or_fails_cleanly(root, manifest)


@settings(max_examples=examples(40), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=NAMES)
def test_a_renamed_shard_never_leads_outside(collected: Path, name: str) -> None:
    manifest = json.loads((collected / MANIFEST).read_text())
    old = manifest["units"][0]["name"]
    manifest["units"][0]["name"] = name
    manifest["shards"][name] = manifest["shards"].pop(old)
    for root in _workspace(collected):
        _check_opens_or_fails_cleanly(root, manifest)
