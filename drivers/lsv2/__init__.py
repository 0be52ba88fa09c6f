"""HEIDENHAIN TNC over LSV2 (TNCremo's protocol) with pylsv2: files, program state, results."""
