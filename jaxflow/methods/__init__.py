"""The flow methods by name (`registry`: network, nsfp, optimise, lidar; one module each with a
`METHOD`, jaxflow.methods.interface). Built from the engines of jaxflow.refine (objectives,
optimisers, rigid clusters, rigid bodies); it imports jaxflow.refine, jaxflow.lidar (the lidar
method), jaxflow.network, jaxflow.geometry and jaxflow.errors; nothing above.
"""
