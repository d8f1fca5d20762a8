"""The per-pair flow refinement engines the methods (jaxflow.methods) are built from: the
objectives (`objectives`: Chamfer terms, smoothness; `distance_grid`: the grid read), the
optimisers (`optimiser`: NSFP and the refinement of a starting flow; `progress`: theirs on
stderr), piecewise rigidity (`rigid_clusters`) and the rigid-bodies stage (`bodies`). It imports
jaxflow.geometry and jaxflow.network (the layers' precisions); nothing above.
"""
