"""The flow methods by name (`registry`: network, nsfp, optimise, lidar; one module each with a
`METHOD`, jaxflow.methods.interface), the objectives (`objectives`: Chamfer terms, smoothness;
`distance_grid`: the grid read), the optimisers (`optimiser`: NSFP and the refinement of a starting
flow; `progress`: theirs on stderr), piecewise rigidity (`rigid_clusters`) and the rigid-bodies
stage (`bodies`). It imports jaxflow.lidar (the lidar method), jaxflow.network, jaxflow.geometry
and jaxflow.errors; nothing above.
"""
