"""A long phase watched: its progress on the terminal and scalars in TensorBoard."""
