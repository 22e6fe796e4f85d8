"""The Rerun bridge node (--rerun): the graph's topics into a Rerun viewer."""
