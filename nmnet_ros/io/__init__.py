"""Data in and out: sequence folders and the dataset layouts read, recordings (.bag, .db3, .mcap), the output
recording, feature caches, labelled pairs, and the rules for what a tool may write."""
