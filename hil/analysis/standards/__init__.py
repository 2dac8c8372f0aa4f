"""Standards and fixed geometric methods: ISO 9283, joint axes from sweeps, the flange-hole geometry."""
