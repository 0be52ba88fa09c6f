"""The daemon's operator web page (see ``daemon.hmi.app``)."""
