"""How jaxflow's tools run, not what they compute: config files on the command line (`configfile`),
JAX's persistent compilation cache (`compile_cache`), run-to-run identical results (`determinism`),
malloc keeping freed memory (`host_memory`) and runs over many processes (`distributed`). It imports
jaxflow.errors only.
"""
