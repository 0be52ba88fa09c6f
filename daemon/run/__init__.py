"""One verification run on one machine: session state machine, capture, re-probing, after-run."""
