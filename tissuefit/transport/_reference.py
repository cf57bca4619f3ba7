def trace_reference(scene, *, photons, seed, tallies=None, options=None):
    raise NotImplementedError("being written")
