"""The simulated hospital: world generation, rendering, sensor models, scenarios."""
