"""Each stage as the pipeline plans it, light to import: its NAME, the stages it reads (DEPENDS), its VERSION, its
typed Settings (each field with its help) and, for a stage that reads the user's input, the `fingerprint` of that input.
Planning, cache keys, `status` and `settings` read these; running a stage imports its work (stages/<name>.py)."""
