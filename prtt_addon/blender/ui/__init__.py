"""What the user touches: properties, operators and panels."""
