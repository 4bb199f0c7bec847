"""The tracking service: command line entry points (the tracker and Zenoh node come next)."""
