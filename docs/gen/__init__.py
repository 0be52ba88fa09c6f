"""The manual's reference pages, generated from the code (``python -m docs.gen``): commands from
the argument parsers, configuration keys from the pydantic schemas, file formats and address maps
from the tables the readers and links use — so the manual cannot disagree with the code."""
