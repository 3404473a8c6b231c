"""Tasks: one module per task (``reach.py``), and the registry of tasks and their gymnasium ids (``registry.py``)."""
