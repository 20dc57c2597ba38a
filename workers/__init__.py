"""Workers: processes that claim jobs from the database queue and run them (``workers/main.py``)."""
