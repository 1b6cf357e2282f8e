"""The BOP ``ycbv`` format: the layout's names and PLY files (:mod:`.format`), the dataset
reader (:mod:`.reader`), the writer (:mod:`.writer`) and the results CSV (:mod:`.results`).

Reader and writer are the two halves of one format and change together: the tests read back
what is written. Layout under a root (bop_toolkit's
``docs/bop_datasets_format.md``)::

    models/obj_0000NN.ply             model meshes, millimetres (ascii or binary PLY)
    models/models_info.json           per obj_id: diameter, min_x.., size_x.. (mm),
                                      symmetries_discrete, symmetries_continuous
    test/SSSSSS/depth/IIIIII.png      uint16 depth; x depth_scale = millimetres
    test/SSSSSS/mask/IIIIII_GGGGGG.png       silhouette of annotation GGGGGG (alone)
    test/SSSSSS/mask_visib/IIIIII_GGGGGG.png its visible part (255 = object)
    test/SSSSSS/rgb/IIIIII.png        colour (optional)
    test/SSSSSS/scene_gt.json         {im_id: [{obj_id, cam_R_m2c (9, row-major), cam_t_m2c (mm)}]}
    test/SSSSSS/scene_camera.json     {im_id: {cam_K (9, row-major), depth_scale}}
    test/SSSSSS/scene_gt_info.json    {im_id: [{px_count_all, px_count_visib, visib_fract, ..}]}
    train_real/SSSSSS/...             training images, the same files
    test_targets_bop19.json           [{scene_id, im_id, obj_id, inst_count}]: the BOP19 targets

How it maps onto the YCB-Video layout, so one :class:`~cloudpose.data.ycb.Frame` and one segment
pipeline serve both:

- obj_id i is YCB-Video class id i (the order of ``classes.txt``).
- A frame's id is YCB-Video's ``SEQ/FRAME``: scene 48, image 1 is ``0048/000001`` in both
  layouts, so its segments (whose FPS start is seeded by the frame id) and its index in the
  toolbox's ``keyframe.txt`` (PoseCNN's results) are the same.
- The label image is built from the per-annotation ``mask_visib`` images (YCB-Video labels by
  class, at most one instance of a class per frame; a frame with two is refused).
- Frames: "keyframe" (or "test") = the images of ``test_targets_bop19.json``; "all" = every
  image of ``test/``; "train" = every image of ``train_real/``. The instances of a frame are
  every annotated object of ``scene_gt.json``, as the YCB-Video toolbox counts them (BOP19's
  targets leave out objects less than 10% visible; the targets only choose the images).
- The occlusion factor's alone-pixel count is ``px_count_all`` of ``scene_gt_info.json``.

Model frame and points (our decision): BOP's ycbv models are YCB-Video's in millimetres with
the origin moved to the centre of the bounding box of the toolbox's evaluation point set
(``points.xyz``, :func:`model_origin`): ``x_bop = 1000 (x - c)``, hence ``R_bop = R`` and
``t_bop = 1000 (t + R c)``. (The per-object offsets published with BOP-to-toolbox converters,
e.g. dornik/sporeagent ``dataset/ycbv_offsets.json``, equal ``c`` to 1e-13 mm.) The reader
converts BOP poses into the toolbox frame and every metric, ICP and the symmetry table use the
toolbox's 2,620-point sets that ship in the package, never the BOP meshes' vertices: AD/ADS
numbers stay the toolbox's on either layout. :func:`read_ply_vertices` reads a BOP model and
:meth:`BOPYcbv.check_models` tells whether its vertices are the toolbox points in that frame.
Results written for BOP (:func:`write_results_csv`) are converted back.
"""

from cloudpose.data.bop.format import (
    CSV_HEADER,
    bop_ids,
    frame_id_of,
    is_bop_root,
    model_origin,
    read_ply_vertices,
)
from cloudpose.data.bop.reader import BOPYcbv
from cloudpose.data.bop.results import (
    check_results_csv,
    check_results_destination,
    write_evaluation_csv,
    write_results_csv,
)
from cloudpose.data.bop.writer import ExportSummary, export_bop, models_info

__all__ = [
    "CSV_HEADER",
    "BOPYcbv",
    "ExportSummary",
    "bop_ids",
    "check_results_csv",
    "check_results_destination",
    "export_bop",
    "frame_id_of",
    "is_bop_root",
    "model_origin",
    "models_info",
    "read_ply_vertices",
    "write_evaluation_csv",
    "write_results_csv",
]
