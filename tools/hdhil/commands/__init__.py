"""One module per ``hdhil`` subcommand; each is imported only when its command runs."""
