"""The data contract: the dataset columns and units, JSON conversion, and the campaign store."""
