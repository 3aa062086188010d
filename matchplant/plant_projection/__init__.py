"""Step 8: put detected plants on the map through the camera poses and the DSM (MatchPlant's key idea).

Plants are detected on the (undistorted) photos; each box is then projected onto the map:

1. rays through the box outline (its corners and points along its edges) leave the camera
   (:meth:`Shot.ray_directions`, exact for perspective, brown and fisheye cameras) and are intersected
   with the real surface (:func:`matchplant.core.geometry.ground.rays_to_ground`) - not a flat plane at the lowest
   height, which is what the published code did: edges facing the image's nadir point (leaf tips on the
   soil) meet the ground estimated from the DSM, the others the DSM itself (they may show the plant's top);
2. the hits form the plant's polygon in the project's CRS; its centroid and an axis-aligned box follow;
3. a plant seen in several photos (85 % overlap: dozens of views) or in two tiles becomes one record:
   views are merged in map space, the view closest to nadir is kept (or the views are fused), and the
   number of views and the spread of their centroids are kept as an uncertainty measure.

Boxes that cannot be projected (image not in the reconstruction, box outside the image, rays that fall
into a DSM hole or leave the DSM) are listed with the reason in ``unprojected_boxes.csv``, never dropped
silently. ``mode: evaluate`` compares projected plants with boxes drawn on the orthophoto.

Modules: ``config`` (the settings), ``settings`` (those of the projection as one record), ``inputs`` (the DSM,
checked before any ray is cast; the predictions are checked where they are read, in ``core/formats/predictions``),
``geometry`` (one image's boxes: rays to the surface, map boxes), ``dsm`` (reading the DSM around the rays),
``views`` (predictions to projected views, or reasons), ``merge`` (views of one plant into one record),
``output`` (GeoPackage, CSV, shapefile), ``evaluation`` (against reference boxes, and the figure), ``run`` (the
step from its config). A run writes into a staging folder moved into place at the end: a failed run leaves
``output_dir`` as it was (only ``unprojected_boxes.csv`` is kept when no box at all could be projected, to say
why).
"""

from matchplant.plant_projection.config import PlantProjectionConfig
from matchplant.plant_projection.run import run

__all__ = ["PlantProjectionConfig", "run"]
