"""Command-line tools and the in-process composition of the three layers."""
