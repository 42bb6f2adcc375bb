"""Commands that are not DVC stages (conversion and inspection tools)."""
