"""Running the node graph: the tier above the nodes (``run_files``: options, parameters and the
files a run leaves; ``pipeline``: starts the nodes and drives a run to its end; ``graph_watch``:
the runner's observer of the graph and its steps, public for harnesses that start the nodes their
own way)."""
