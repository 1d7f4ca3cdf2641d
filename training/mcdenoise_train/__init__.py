"""Python side of mcdenoise: the network, its training and export, and the data generator."""
