"""One module per stage's work (its `run`); what the pipeline plans each stage by (its settings, inputs and version)
is in stages/settings/. pipeline/stage.py says what each defines."""
