"""refine: region-wise progressive refinement (RPR) of the inpainted views' low-detail blocks.

In: ``inpaint`` (images, source lists) and ``remove`` (holes, the context images the sources point into,
cameras and completed depth). Out:

* ``images/<view>.png``: the refined views;
* ``refined/<view>.png``: visualisation (refined blocks outlined: yellow once, orange twice, red more);
* ``refined.json``: per view the blocks measured, found low-detail, refined (with how often), still
  low after the last round, and the rounds used.

Blocks: SBM's target blocks with their ranked source lists (``inpaint``'s ``source/<view>.npz``);
when the inpainter left none (the ``opencv`` backend), target blocks are laid over the view's
inpainted pixels and ``candidates`` sources are retrieved for them by SBM's block matching against
the current fill, so RPR also sharpens a smooth baseline fill (the paper's setting: a blurry initial
inpainting refined block by block).

With ``propagate`` (default) and a multi-view inpaint, the reference view is refined first and its
refined fill is carried again into the pixels the other views had taken from it, so the views stay
consistent; then each view refines its own SBM blocks.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sgpor_pipeline.dag import Stage, StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.hashing import hash_obj
from sgpor_pipeline.imageio import read_image, read_labels, to_float32, write_png
from sgpor_pipeline.removal.multiview import FILLED_PROJECTED, load_remove_folder, warp_from_reference
from sgpor_pipeline.removal.rpr import RPRParams, hf_energy, refine_view, refined_overlay
from sgpor_pipeline.removal.sbm import SBMParams, build_source_bank, match_blocks, target_positions


@dataclass
class RefineParams:
    ratio: float = 0.15  # low-detail: HF energy below ratio x the surrounding's
    max_rounds: int = 3  # K
    erode: int = 2
    ring: int = 0  # surrounding width in pixels; 0 = block size
    propagate: bool = True  # re-project the refined reference into the other views' projected pixels
    depth_tol: float = 0.02
    candidates: int = 8  # sources retrieved per block when the inpainter left no list (opencv backend)
    seed: int = 0

    def rpr(self) -> RPRParams:
        return RPRParams(ratio=self.ratio, max_rounds=self.max_rounds, erode=self.erode, ring=self.ring)


class RefineStage(Stage):
    name = "refine"
    # 2: with max_rounds = 0 no sources are retrieved for another inpainter's fill; 3: the alignment
    # search coarse to fine from a radius of 5 px (SBMParams.shift_step)
    VERSION = 3
    Params = RefineParams
    inputs = ("inpaint", "remove")
    libraries = ("torch", "kornia")

    def run(self, ctx: StageContext) -> None:
        p: RefineParams = ctx.params
        rp = p.rpr()
        inp = Path(ctx.inputs["inpaint"])
        data = load_remove_folder(ctx.inputs["remove"])
        names = data.names
        report_in = json.loads((inp / "inpaint.json").read_text())
        block = int(report_in.get("block_size", 15))
        ref_name = report_in.get("reference") if p.propagate else None
        digests = {v.name: [ctx.file_digest(f) for f in v.files()] for v in data.views}
        all_key = hash_obj(digests)
        state: dict[str, object] = {}

        def sources() -> tuple[list[np.ndarray], list[np.ndarray]]:
            if "src" not in state:
                imgs = [v.context8() for v in data.views]  # (uint8: held for every view)
                state["src"] = (imgs, [hf_energy(to_float32(im)) for im in imgs])
            return state["src"]

        sbm = SBMParams(block_size=block, top_k=p.candidates, seed=p.seed)

        def bank():
            if "bank" not in state:
                state["bank"] = build_source_bank(names, sources()[0], [v.mask() for v in data.views],
                                                  [v.hole() for v in data.views], sbm)
            return state["bank"]

        def build(folder: Path, name: str, ref_item: Path | None) -> None:
            t0 = time.perf_counter()
            view = data.by_name(name)
            hole = view.hole()
            img = read_image(inp / "images" / f"{name}.png")
            filled_from = read_labels(inp / "filled_from" / f"{name}.png")
            src = np.load(inp / "source" / f"{name}.npz")
            src_names = [str(s) for s in src["views"]]
            if src_names != names:
                raise PipelineError("the inpaint stage's source lists refer to other views than the remove stage's",
                                    path=inp / "source" / f"{name}.npz", fix="rerun inpaint (--force inpaint)")
            reprojected = 0
            if ref_item is not None:
                rv = data.by_name(ref_name)
                ref_img = read_image(ref_item / "image.png")
                ref_hole = rv.hole()
                target = filled_from == FILLED_PROJECTED
                cols, got = warp_from_reference(ref_img, rv.camera, rv.depth(), ref_hole, view.camera,
                                                view.depth(), target, "backward", p.depth_tol)
                img[got] = cols[got]
                reprojected = int(got.sum())
            imgs, energies = sources()
            own = hole & (filled_from != FILLED_PROJECTED)
            targets, cand, first_used = src["targets"], src["cand"], True
            if len(targets) == 0 and own.any() and rp.max_rounds > 0:  # another inpainter: retrieve sources now
                targets = target_positions(own, block, sbm.target_stride, sbm.tau)
                cand = match_blocks(img, np.ones(own.shape, bool), targets, bank(), sbm)[0]
                first_used = False
            res = refine_view(img, own, targets, cand, imgs, rp, block, energies, first_used)
            write_png(folder / "image.png", res.image)
            write_png(folder / "refined.png", refined_overlay(res.image, targets, res.count, block, hole))
            blocks = [[int(y), int(x), int(c)] for (y, x), c in zip(targets, res.count) if c > 0]
            info = dict(res.info, reprojected=reprojected, refined=blocks, retrieved=not first_used,
                        seconds=time.perf_counter() - t0)
            (folder / "info.json").write_text(json.dumps(info))

        (ctx.out_dir / "images").mkdir()
        (ctx.out_dir / "refined").mkdir()
        views_with_hole = [n for n in names
                           if (inp / "source" / f"{n}.npz").is_file() and data.by_name(n).hole().any()]
        order = ([ref_name] if ref_name in views_with_hole else []) + [n for n in views_with_hole if n != ref_name]
        items: dict[str, Path] = {}
        ref_digest = None
        for name in ctx.progress(order, total=len(order), desc="refine"):
            is_ref = name == ref_name
            ref_item = items.get(ref_name) if (ref_name and not is_ref and data.has_geometry) else None
            key = {"view": name, "remove": all_key, "block": block,
                   "inpaint": [ctx.file_digest(inp / sub / f"{name}.{ext}")
                               for sub, ext in (("images", "png"), ("filled_from", "png"), ("source", "npz"))],
                   "ref": ref_digest if ref_item is not None else None}
            items[name] = ctx.cached_item(key, lambda folder, n=name, r=ref_item: build(folder, n, r))
            if is_ref:
                ref_digest = ctx.file_digest(items[name] / "image.png")
        summary: dict[str, dict] = {}
        for name in names:
            if name in items:
                item = items[name]
                (ctx.out_dir / "images" / f"{name}.png").write_bytes((item / "image.png").read_bytes())
                (ctx.out_dir / "refined" / f"{name}.png").write_bytes((item / "refined.png").read_bytes())
                summary[name] = json.loads((item / "info.json").read_text())
            else:
                (ctx.out_dir / "images" / f"{name}.png").write_bytes((inp / "images" / f"{name}.png").read_bytes())
        if (inp / "relit").is_dir():  # inpaint.lift_shadow: the pixels relit outside the holes, for the finetune
            shutil.copytree(inp / "relit", ctx.out_dir / "relit")
        report = {
            "ratio": p.ratio, "max_rounds": p.max_rounds, "reference": ref_name, "views": summary,
            "refined_blocks": sum(s["refined_blocks"] for s in summary.values()),
            "low_before": sum(s["low_before"] for s in summary.values()),
            "low_after": sum(s["low_after"] for s in summary.values()),
            "seconds_views": sum(s["seconds"] for s in summary.values()),
        }
        (ctx.out_dir / "refined.json").write_text(json.dumps(report, indent=1))
        ctx.notes.update(refined_blocks=report["refined_blocks"], low_before=report["low_before"],
                         low_after=report["low_after"])
