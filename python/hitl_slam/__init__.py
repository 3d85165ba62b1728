"""hitl-slam: Human-in-the-Loop SLAM (placeholder while the core is being built)."""
