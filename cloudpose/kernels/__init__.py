"""Compiled (numba) kernels for the point-cloud hot loops: exact FPS, bounded nearest neighbours,
the ICP loop and ADS, one algorithm per module; and one per-pixel pass of the depth sensor.

Three hot loops of the pipeline do per-point work that numpy can only express as many small
calls, so they run here as compiled loops:

- ``fps.fps_order``: exact farthest point sampling (data/segments.py). A k-d tree groups the
  points into buckets; after each pick, a subtree is skipped when no point in it can get closer
  to the new sample than it already is to an earlier one (its box is farther than the largest
  nearest-sample distance inside it). The distances are the same float32 expressions as the
  numpy loop and ties go to the highest index (fpsample's rule), so the order is the same,
  index for index.
- ``icp.icp_model_frame``: the paper's ICP schedule in the model frame (refine.py): per
  iteration, each observed point's nearest model point within the radius, the correspondence
  moments, and Umeyama's rotation. A point's first neighbour comes from a bounded k-d tree
  search; later ones from a walk over the model's Delaunay graph from its previous neighbour,
  skipped while the point cannot have left that neighbour's Voronoi cell.
- ``ads.adds_mean``: ADS of many instances of one model (metrics.py): each ground-truth-posed
  point in the estimate's model frame, its nearest model point, by a downhill walk over the
  Delaunay graph from the point's own model point or the previous point's neighbour. A point
  whose Delaunay neighbours are all farther from the query than itself has the query in its
  Voronoi cell: the walk's end is the exact nearest point.

Four serve on-line synthesis version 2 (``data.online_version = 2``,
:mod:`cloudpose.data.synth.online`): ``sensor`` (the depth jump and incidence cosine of every
object pixel, the exact edge distance and the readings of a scene in one pass), ``raster`` (a
z-buffer of the object meshes: the depth a ray cast through the pixel centres gives),
``segment_cut`` (each instance's pixels gathered and an exact FPS over a grid of buckets, the
same order as ``fps``) and ``placement`` (the slide of a table scene's new object, which
version 1's scenes use too: the same steps as the numpy loop). ``scene_pass`` serves version 3:
a scene's objects into one z-buffer, every object pixel's sensor reading, back-projection and
outlier filter in one pass, and an exact FPS over coordinate-wise buckets.

The structures they share: ``kdtree`` (a k-d tree of arrays and its bounded search) and
``graph`` (a model's k-d tree with its Delaunay graph, or each point's nearest points where a
model has no 3-D triangulation: flat or under 5 points).

Every kernel has a slow twin elsewhere (numpy loop FPS, ten Open3D calls, per-instance KD-tree
ADS) with tests that they agree. ``backend`` is the one switch between them: callers ask
``enabled()`` (through ``kernels.model_index.ModelIndex`` and ``fps.farthest_order``), never numba
itself. Compiled code is cached on disk (``cache=True``), so only the first run on a machine
pays the compilation (a few seconds).
"""

from cloudpose.kernels.ads import adds_mean
from cloudpose.kernels.backend import HAVE_NUMBA, disabled, enabled
from cloudpose.kernels.fps import farthest_order, fps_order
from cloudpose.kernels.graph import NNIndex, build_nn_index
from cloudpose.kernels.icp import icp_model_frame
from cloudpose.kernels.kdtree import KDTree, build_kdtree, nearest_bounded

__all__ = [
    "HAVE_NUMBA",
    "KDTree",
    "NNIndex",
    "adds_mean",
    "build_kdtree",
    "build_nn_index",
    "disabled",
    "enabled",
    "farthest_order",
    "fps_order",
    "icp_model_frame",
    "nearest_bounded",
]
