"""Route modules: health (no auth), datasets and assets (API key when configured)."""
