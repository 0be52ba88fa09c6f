"""What several packages share: messages, jobs and verdict codes, file schemas and
their YAML reader, the probing-log format, protocol tables."""
