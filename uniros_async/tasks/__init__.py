"""Tasks: one module per task, each registering its gymnasium ids (reach.py)."""
