"""Each stage as the pipeline plans it, light to import: its NAME, the stages it reads (DEPENDS), its VERSION, its
typed Settings (each field with its help) and, for a stage that reads the user's input, the `fingerprint` of that input.
Planning, cache keys, `status` and `settings` read these; running a stage imports its work (stages/<name>.py).

A stage's Settings extend the options classes of the libraries it drives (plenoxels.core.options, stages/sfm/options.py,
stages/framing/options.py), each of which holds its options' defaults, help and `check`; the Settings' own `check`
runs those checks and then checks only the fields the stage adds."""
