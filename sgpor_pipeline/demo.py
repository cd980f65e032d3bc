"""The embedded demo: a synthetic scene the package generates itself (no download, no data folder)."""

from __future__ import annotations

import logging
from pathlib import Path

from .hashing import canonical_json

log = logging.getLogger("sgpor_pipeline")


def ensure_demo_scene(folder: Path, params: object) -> Path:
    """Generate the synthetic scene into ``folder`` unless it already holds the scene of ``params``."""
    from .synthetic import generate_scene, save_scene

    folder = Path(folder)
    stamp = folder / "scene_params.json"
    wanted = canonical_json(params)
    if stamp.is_file() and stamp.read_text() == wanted:
        return folder
    log.info(f"generating the synthetic demo scene in {folder}")
    scene = generate_scene(params)
    save_scene(scene, folder)
    stamp.write_text(wanted)
    return folder

