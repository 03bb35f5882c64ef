"""The hierarchical mapper (`colmap-ext hierarchical_mapper`, cli.py): COLMAP's command for
large sets, with our mapper.

The view graph (images joined by verified pairs, weighted by their inliers) is cut into
clusters of at most `--leaf_max_num_images` images by recursive bisection, and each
cluster grows by `--image_overlap` outside images, shared out among the clusters it links
to, each giving its images most connected to it (partition.py). Each cluster is mapped
on its own by the calibrated mapper (mapper.pipeline.reconstruct, with fewer global
adjustments: MAPPER_DEFAULTS; clusters.py): a Ray task with `--ray_address`, else a
process of a local pool of `--num_workers`. The cluster models are then brought into one frame along a maximum
spanning tree of their overlaps, each link the similarity their shared images agree on
(merging.py's rule: rotations and directions of the centres within a few degrees; the
rotation from the shared images' own rotations, which fix it where their centres, along
a walk, nearly lie on a line), and points that share an observation become one
(joining.py). The flat mapper then ends each joined model as it ends its own, which the
clusters left out: it continues the model over its clusters' images (registering those a
cluster missed), adjusts it, triangulates it again and filters it (pipeline.py).
Output as COLMAP's: OUTPUT/0, OUTPUT/1, ... (one per group of clusters that joined).
"""

from colmap_ext.hierarchical_mapper.clusters import ClusterModel
from colmap_ext.hierarchical_mapper.joining import similarity
from colmap_ext.hierarchical_mapper.options import MAPPER_DEFAULTS, HierarchicalOptions
from colmap_ext.hierarchical_mapper.partition import partition
from colmap_ext.hierarchical_mapper.pipeline import hierarchical_mapping

__all__ = ["MAPPER_DEFAULTS", "ClusterModel", "HierarchicalOptions", "hierarchical_mapping",
           "partition", "similarity"]
