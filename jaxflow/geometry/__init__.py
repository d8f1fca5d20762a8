"""Geometry every other part shares: every nearest-neighbour search, on the host and in compiled
programs, and neighbourhood normals (`neighbours`), distances, row chunks and gathers in jax
(`ops`), rigid motions, the one Kabsch fit and the one rotation of a rotation vector (`rigid`),
the one robust registration core (`registration`), the up axis and the model frame (`frames`),
what a sensor at the origin saw (`visibility`), rigid groups and the rule that judges them
(`groups`). It imports only jaxflow.errors; everything else may import it.
"""
