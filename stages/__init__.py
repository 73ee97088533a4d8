"""One module per stage; see pipeline/stage.py for what a stage module defines."""
