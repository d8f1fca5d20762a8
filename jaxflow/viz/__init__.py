"""Pictures: the Fig. 2 view, error maps and top views of a sweep (`figures`), the 3D HTML viewer
(`viewer`) and a run's learning curve (`curves`). matplotlib is loaded here only. It imports
jaxflow.geometry and jaxflow.errors only.
"""
