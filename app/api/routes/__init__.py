"""One router per resource: sessions, jobs, maps, keys, and the system endpoints."""
