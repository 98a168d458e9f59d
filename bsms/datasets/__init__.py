"""The field's benchmark datasets, read without TensorFlow: DeepMind's MeshGraphNets TFRecords
(:mod:`bsms.datasets.deepmind`) and the BSMS-GNN authors' one-``.h5``-per-trajectory files
(:mod:`bsms.datasets.authors`). Both give trajectories as ``{field: array (T, ...)}``; errors
name the file, the record and the field (:class:`SourceError`).
"""

from bsms.datasets.errors import SourceError

__all__ = ["SourceError"]
