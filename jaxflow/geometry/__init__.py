"""Geometry every other part shares: nearest neighbours and gathers in jax (`ops`), the host's
k-d tree and neighbourhood normals (`neighbours`), rigid motions and the one Kabsch fit (`rigid`),
the one robust registration core (`registration`), the up axis and the model frame (`frames`),
what a sensor at the origin saw (`visibility`), rigid groups and the rule that judges them
(`groups`). It imports only jaxflow.errors; everything else may import it.
"""
