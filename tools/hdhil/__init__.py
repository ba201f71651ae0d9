"""hdhil host tools: simulated CAN bus, DBC codecs, trace logging, dump and the `hdhil` command."""
