"""Schema revisions, one file each, named ``YYYY_MM_DD_HHMM_<slug>.py``."""
