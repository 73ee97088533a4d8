"""The export stage's own library (stages/export.py): what it plans before it runs."""
