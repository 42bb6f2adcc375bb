"""Commands that are not DVC stages (same rules as pipeline/stages: light top-level imports)."""
