"""Alembic environment and revisions of pipescan's database (see ``pipescan.storage.database.db``).

A package so that it is installed with pipescan; Alembic loads ``env.py`` and the files in
``versions/`` itself, by path.
"""
