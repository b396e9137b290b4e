"""The profile stage's helpers: its typed result (`result`, what profile.json holds), the material it proposes
(`proposal`) and its figures (`figures`)."""
