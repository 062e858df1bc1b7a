"""Prefect tasks: thin wrappers that read, call the pure core and write.

Every task is declared with ``cache_policy=NO_CACHE``. Prefect 3's default policy hashes each
task run's inputs (the staged archive's metadata with every frame, the whole trajectory, the
registration evidence): about 9 ms for the metadata and 4 ms for the trajectory of a 2,000-frame
scan, for each of the run's tasks, growing with the scan, and under the GIL. pipescan's tasks
write scratch files and the database, so a cached result would be wrong anyway; a scan already
inspected is found by its content hash instead (``reuse_stored``).
"""
