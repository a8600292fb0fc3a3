"""Reading what users upload: scans and the captures that come with them."""
