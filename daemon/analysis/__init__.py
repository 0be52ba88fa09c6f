"""One run's numbers: hits to ball centres, identification, verdict against tolerances."""
