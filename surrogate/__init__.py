"""surrogate package (see DESIGN.md section 2)."""
