"""The recorder node (--record): the graph's topics into an mcap bag."""
