"""Per-pair flow methods, no training needed: the registry of methods (`registry`: network,
nsfp, optimise; their settings and flow functions), the objectives (`objectives`: Chamfer terms,
smoothness; `distance_grid`: the grid read), the optimisers (`optimiser`: NSFP and the refinement
of a starting flow), piecewise rigidity (`rigid_clusters`) and the rigid-bodies stage (`bodies`).
It imports jaxflow.network, jaxflow.geometry and jaxflow.errors; not jaxflow.lidar, nor anything
above.
"""
