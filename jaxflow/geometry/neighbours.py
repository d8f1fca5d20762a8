"""Nearest neighbours on the host (NumPy): the one entry point to scipy's k-d tree, and the
spread of each point's neighbourhood (normals, lines).

    tree = Tree(points_Mx3)
    d_N, j_N = tree.nearest(query_Nx3, reach=0.5)     # inf / M where nothing is within reach
    nbr_NxK = tree.knn(query_Nx3, k)                  # nearest first
    values_NxD, vectors_NxDxD = local_spread(points_NxD, k)   # ascending; vectors[:, :, 0]: normal

Inside compiled programs the nearest-neighbour search is jaxflow.refine.objectives.knn (the host
search there is this Tree through a callback) and jaxflow.geometry.ops.knn (brute force in jax).
"""

import os

import numpy as np
from scipy.spatial import cKDTree

# A query of fewer neighbours than this (points x k) runs on one thread: starting threads costs
# more than such a query (an ICP round's 4000 points; 17 of 43 s of three pairs went to
# Thread.start on a loaded 2-core machine when every query used all cores). The answers do not
# depend on the threads.
THREADED_WORK = 100_000
THREADS = max(1, min(4, os.cpu_count() or 1))


class Tree:
  """scipy's cKDTree of `points_MxD` (float64), queried with as many threads as the query is worth."""

  def __init__(self, points_MxD):
    self.points = np.asarray(points_MxD, np.float64)
    self.kd = cKDTree(self.points)

  def _workers(self, queries: int, k: int) -> int:
    return THREADS if queries * k >= THREADED_WORK else 1

  def nearest(self, query_NxD, reach: float = np.inf):
    """(distance N, index N) of each query's nearest point; (inf, M) where none is within `reach`."""
    query = np.asarray(query_NxD, np.float64)
    return self.kd.query(query, distance_upper_bound=reach, workers=self._workers(len(query), 1))

  def knn(self, query_NxD, k: int, reach: float = np.inf, distances: bool = False):
    """Indices N x k' (k' = min(k, M), nearest first; M beyond `reach`), with the distances when
    `distances`."""
    query = np.asarray(query_NxD, np.float64)
    k = min(k, len(self.points))
    d, j = self.kd.query(query, k=list(range(1, k + 1)), distance_upper_bound=reach,
                         workers=self._workers(len(query), k))
    return (d, j) if distances else j


def knn_graph(points_NxD, k: int) -> np.ndarray:
  """Each point's k nearest points of the same cloud (N x min(k, N), itself first)."""
  return Tree(points_NxD).knn(points_NxD, k)


def local_spread(points_NxD, k: int, tree: Tree | None = None):
  """Eigenvalues (N x D, ascending) and eigenvectors (N x D x D, columns) of the scatter matrix of
  each point's k-neighbourhood: vectors[:, :, 0] is a surface's normal (3-D) or the direction
  across a line (2-D); the values say how flat, thin or round the neighbourhood is."""
  points = np.asarray(points_NxD, np.float64)
  nb = points[(Tree(points) if tree is None else tree).knn(points, k)]
  centred = nb - nb.mean(1, keepdims=True)
  return np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
