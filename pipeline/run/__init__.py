"""The one runner: a plan of stages and sinks, and the passes over a recording's chunks."""
