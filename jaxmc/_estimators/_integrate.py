def integrate(*args, **kwargs):
    raise NotImplementedError("being written")
