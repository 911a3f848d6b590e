"""The RT-Splatting model: surfel parameters, environment feature map, specular network,
deferred shading with reflection/transmission compositing, and specular-aware gradient gating."""
