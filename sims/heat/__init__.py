"""Heat: the layered Pennes cautery with Arrhenius damage, its layers, its display sampling and the burn cross-section."""
