"""Long runs and the command line: streams, manifests, Dask, ``larc``."""
