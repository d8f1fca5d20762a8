"""Raw LiDAR sweeps: the ground (`ground`), the sensor's ego-motion (`ego`), moving objects
(`objects`) and the pipeline that puts them together for every point of a sweep (`sweep`). NumPy
and scipy (small_gicp for the registration), no jax. Their settings are one frozen dataclass a
block (`settings`; `--method.lidar.FIELD=V`). It imports jaxflow.geometry and jaxflow.errors only;
a flow method comes in as a function.
"""
