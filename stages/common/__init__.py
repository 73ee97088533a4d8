"""What every stage shares: its JSON records, media files in and out, frames as the fit sees them, stop requests."""
