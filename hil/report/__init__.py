"""Presentation: a diagnosis and its active rounds in words (terminal), as JSON and as one HTML page."""
