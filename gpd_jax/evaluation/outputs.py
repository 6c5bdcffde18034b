"""Writing an evaluation to disk: `metrics.json`, `tables.txt` and pictures under `render/`, each written to a
temporary and renamed into place, so an interrupted run leaves the previous outputs whole."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from typing import Any

from gpd_jax.evaluation.render import render_items
from gpd_jax.evaluation.report import to_json_compatible
from gpd_jax.fsutil import atomic_write_text, umask_mode


def write_render(out_dir: str, items, task_names: Sequence[str], *, num_history: int, frame_period_s: float,
                 tokenizer=None, size_px: int = 320) -> list[str]:
    """Renders `items` (`RenderItem`s) into a fresh `out_dir/render` that replaces the old one in one rename.
    Returns the file names."""
    tmp = tempfile.mkdtemp(prefix=".render-", dir=out_dir)
    try:
        paths = render_items(items, task_names, tmp, num_history=num_history, frame_period_s=frame_period_s,
                             tokenizer=tokenizer, size_px=size_px)
        final = os.path.join(out_dir, "render")
        if os.path.exists(final):
            old = tempfile.mkdtemp(prefix=".render-old-", dir=out_dir)
            os.replace(final, os.path.join(old, "render"))
            shutil.rmtree(old, ignore_errors=True)
        umask_mode(tmp, directory=True)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return sorted(os.path.basename(p) for p in paths)


def write_evaluation(out_dir: str, results: dict[str, Any], tables: str, items=(), task_names: Sequence[str] = (),
                     *, tokenizer=None, size_px: int = 320) -> dict[str, Any]:
    """Writes pictures of `items` (if any), `tables.txt` and `metrics.json` (strict JSON, NaN as null) to
    `out_dir`; the pictures' files and timing are added to `results`, which is returned."""
    os.makedirs(out_dir, exist_ok=True)
    if items:
        t0 = time.perf_counter()
        files = write_render(out_dir, items, task_names, num_history=int(results["num_history"]),
                             frame_period_s=float(results["frame_period_s"]), tokenizer=tokenizer, size_px=size_px)
        results["timing_s"]["render"] = round(time.perf_counter() - t0, 2)
        results["render"] = {"dir": "render", "files": files,
                             "scenarios": [{"index": it.index, "scenario_id": it.scenario_id} for it in items]}
    atomic_write_text(os.path.join(out_dir, "tables.txt"), tables + "\n")
    atomic_write_text(os.path.join(out_dir, "metrics.json"),
                      json.dumps(to_json_compatible(results), indent=2, allow_nan=False) + "\n")
    return results
