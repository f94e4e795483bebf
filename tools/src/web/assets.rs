//! The page's files, built into the binary (`tools/web/`): ppm-web serves
//! every byte the browser loads, so the page works with no network and
//! nothing but ppm-web to install.

/// One file of the page.
#[derive(Debug, Clone, Copy)]
pub struct Asset {
    /// Its path in URLs.
    pub path: &'static str,
    /// Its media type.
    pub content_type: &'static str,
    /// Its bytes.
    pub body: &'static [u8],
}

/// Every file of the page.
pub const ASSETS: [Asset; 3] = [
    Asset {
        path: "/",
        content_type: "text/html; charset=utf-8",
        body: include_bytes!("../../web/index.html"),
    },
    Asset {
        path: "/app.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_bytes!("../../web/app.js"),
    },
    Asset {
        path: "/style.css",
        content_type: "text/css; charset=utf-8",
        body: include_bytes!("../../web/style.css"),
    },
];

/// The page's size: all its files, bytes.
pub fn page_bytes() -> usize {
    ASSETS.iter().map(|a| a.body.len()).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_loads_nothing_from_elsewhere() {
        for a in ASSETS {
            // SVG's namespace is a name, not a place anything is loaded from.
            let text = std::str::from_utf8(a.body)
                .unwrap()
                .replace("http://www.w3.org/2000/svg", "");
            for outside in ["http://", "https://", "//cdn", "@import", "fonts.g"] {
                assert!(!text.contains(outside), "{} names {outside}", a.path);
            }
        }
        let html = std::str::from_utf8(ASSETS[0].body).unwrap();
        assert!(html.contains("src=\"/app.js\"") && html.contains("href=\"/style.css\""));
        // Small: the whole page well under 64 KiB.
        assert!(page_bytes() < 64 * 1024, "{} bytes", page_bytes());
    }
}
