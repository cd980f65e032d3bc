"""Object removal in image space: fill the holes the deleted object leaves, consistently across views.

Modules (the paper's SBM and RPR steps, CPU-first, DESIGN.md section 7):

* :mod:`~sgpor_pipeline.removal.features`: block descriptors over a block's context window
  (``classical``: Lab colour + contrast + HOG-like orientations + LBP, no weights; ``dinov2``:
  DINOv2-like ONNX patch tokens, optional extra), with valid-pixel-only cell means;
* :mod:`~sgpor_pipeline.removal.sbm`: semantic-guided block matching: source banks over all views,
  matrix-product top-k retrieval, onion-peel completion, feathered + Poisson blending; the OpenCV
  xphoto FSR baseline;
* :mod:`~sgpor_pipeline.removal.rpr`: region-wise progressive refinement of low-detail blocks
  (Sobel high-frequency energy against the surroundings, next-best sources, bounded rounds);
* :mod:`~sgpor_pipeline.removal.multiview`: the ``remove`` stage's folder contract and loader,
  reference-view fill lifted to 3D with the completed depth and carried into the other views, and
  ground-truth fixtures from synthetic scenes.

Submodules are imported on demand (``from sgpor_pipeline.removal.sbm import inpaint_view``); this
package itself imports nothing heavy.
"""
