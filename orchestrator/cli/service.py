"""CLI commands (being built)."""


def register(sub) -> None:
    """Adds this group's commands."""
