"""Scene catalogs: versioned JSON lists of initial scenes, and the generators that make them."""
