"""The ``crowdslam`` command line: each subcommand parses, calls one library function, prints."""
