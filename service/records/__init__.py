"""Dataset records: the Records class is the one door to Redis (store.py; the queue side's coordination, a mixin of
it, in coordination.py), its Lua scripts (scripts.py), the typed record (types.py), and restoring records from the
bucket after Redis lost them (recovery.py)."""
