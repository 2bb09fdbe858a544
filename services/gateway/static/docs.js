// Starts Swagger UI on /docs (services/gateway/security.py serves the page and the bundle from the
// package): a file, not an inline script, since the gateway's Content-Security-Policy allows none.
// No validator: Swagger UI would otherwise send the API description to an outside service.
window.addEventListener("DOMContentLoaded", () => {
  window.ui = SwaggerUIBundle({
    url: "/openapi.json",
    dom_id: "#swagger-ui",
    validatorUrl: null,
    deepLinking: true,
    presets: [SwaggerUIBundle.presets.apis],
    layout: "BaseLayout",
  });
});
