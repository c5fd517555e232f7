"""The `esr` command line (Typer): main.py holds the app and its commands."""
