def trace(scene, *, key, photons, tallies=None, options=None):
    raise NotImplementedError("being written")
