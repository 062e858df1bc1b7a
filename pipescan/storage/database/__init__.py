"""What is kept: the database (SQLAlchemy models, alembic migrations, the repository that
saves and loads inspections), the queries behind reports and trends, and the exports."""
