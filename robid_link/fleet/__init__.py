"""A plant's robots together: each parameter's trend per robot and model version, drift and
wear flags with their evidence, the outliers of each robot type (``analysis.py``), and the
re-identification of many robots' stored logs with another model (``reidentify.py``), as pure
tasks (``tasks.py``) on Dask or in this process (``engine.py``). The caller writes the store."""
