"""The plumbing every part of drgan shares: errors, atomic files, config resolvers, self-contained HTML pages, the
Mitsuba backend, safe checkpoint loading, allow-listed `_target_` builds and progress lines."""
