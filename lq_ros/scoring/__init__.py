"""Scoring: per-episode metrics, chunk-boundary quality, scoring one bag, and aggregates with intervals."""
