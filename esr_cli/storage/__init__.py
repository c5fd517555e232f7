"""The content-addressed store: keys and provenance, the one artifact lifecycle (a `Recipe`
made by `ensure`), checkpoints and metrics on disk, played-episode logs, and `esr export` /
`esr import` archives with their checks (docs/store.md).
"""
