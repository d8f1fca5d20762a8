"""Geometry every other part shares: nearest neighbours and gathers in jax (`ops`), rigid
motions and the one Kabsch fit (`rigid`), the up axis and the model frame (`frames`), what a sensor
at the origin saw (`visibility`). It imports only jaxflow.errors; everything else may import it.
"""
