"""Storage: SQLAlchemy 2 models, database sessions, the job queue and the repository functions.

ORM rows stay inside this package; what leaves it is a plain value (a dataclass or a dict).
"""
