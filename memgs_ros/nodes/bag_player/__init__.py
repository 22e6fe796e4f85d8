"""The bag/folder player node: a source's frames as camera topics."""
