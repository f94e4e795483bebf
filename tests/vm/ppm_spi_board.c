// SPDX-License-Identifier: GPL-2.0
/*
 * ppm_spi_board: board code for the real-kernel SPI test (tests/vm/).
 *
 * x86 QEMU has no device tree, so nothing describes a bit-banged SPI bus.
 * This module does what a board file would: it maps the "sck", "mosi" and
 * "cs" GPIOs of the spi-gpio driver's platform device "spi_gpio.<bus>" to
 * lines of a GPIO chip found by its label (a gpio-sim bank's label), adds
 * that platform device (one chip select), and creates one SPI device on the
 * resulting bus (mode 0, chip select 0) with a modalias no driver claims, so
 * that the test binds spidev to it through driver_override:
 *
 *   insmod spi-bitbang.ko; insmod spi-gpio.ko
 *   insmod ppm_spi_board.ko chip=ppm-spi sck=0 mosi=1 cs=2 bus=0
 *   echo spidev > /sys/bus/spi/devices/spi0.0/driver_override
 *   echo spi0.0 > /sys/bus/spi/drivers/spidev/bind      # -> /dev/spidev0.0
 *
 * Written against Linux 6.1 (Debian's linux-source-6.1): spi-gpio takes its
 * lines through gpiod lookups (con_id "sck", "mosi", optional "miso", and
 * "cs" index 0..num_chipselect-1) and needs platform data with
 * num_chipselect; spi_busnum_to_master() no longer exists and
 * spi_register_board_info() is not exported, so the controller is found as
 * the child device ("spi<bus>") of the platform device, which spi-gpio's
 * probe registers synchronously when spi-gpio.ko is already loaded.
 *
 * Test code only; not part of ppm's own (MIT OR Apache-2.0) sources.
 */
#include <linux/module.h>
#include <linux/platform_device.h>
#include <linux/gpio/machine.h>
#include <linux/spi/spi.h>
#include <linux/spi/spi_gpio.h>
#include <linux/slab.h>
#include <linux/string.h>

static char *chip = "ppm-spi";
module_param(chip, charp, 0444);
MODULE_PARM_DESC(chip, "label of the GPIO chip carrying the lines");
static uint sck;
module_param(sck, uint, 0444);
MODULE_PARM_DESC(sck, "line offset of SCK on the chip");
static uint mosi = 1;
module_param(mosi, uint, 0444);
MODULE_PARM_DESC(mosi, "line offset of MOSI on the chip");
static uint cs = 2;
module_param(cs, uint, 0444);
MODULE_PARM_DESC(cs, "line offset of the chip select (active low) on the chip");
static int bus;
module_param(bus, int, 0444);
MODULE_PARM_DESC(bus, "SPI bus number (platform device spi_gpio.<bus>, /dev/spidev<bus>.0)");
static uint max_hz = 20000000;
module_param(max_hz, uint, 0444);
MODULE_PARM_DESC(max_hz, "max_speed_hz of the SPI device (spi-gpio bit-bangs as fast as gpiolib goes anyway)");

static struct gpiod_lookup_table *lookup;
static struct platform_device *pdev;
static struct spi_device *spi;

static int match_name(struct device *dev, void *name)
{
	return strcmp(dev_name(dev), name) == 0;
}

static int __init ppm_spi_board_init(void)
{
	struct spi_gpio_platform_data pdata = { .num_chipselect = 1 };
	struct spi_board_info info = {
		.modalias = "ppm-spi-sink",	/* no driver has this name */
		.max_speed_hz = max_hz,
		.bus_num = bus,
		.chip_select = 0,
		.mode = SPI_MODE_0,
	};
	struct spi_controller *ctlr;
	struct device *dev;
	char name[16];
	int ret;

	if (bus < 0 || bus > 255 || !chip || !*chip)
		return -EINVAL;
	if (sck > 0xfffe || mosi > 0xfffe || cs > 0xfffe)
		return -EINVAL;

	/* Three entries and the empty terminator. */
	lookup = kzalloc(struct_size(lookup, table, 4), GFP_KERNEL);
	if (!lookup)
		return -ENOMEM;
	lookup->dev_id = kasprintf(GFP_KERNEL, "spi_gpio.%d", bus);
	if (!lookup->dev_id) {
		ret = -ENOMEM;
		goto err_lookup;
	}
	lookup->table[0] = (struct gpiod_lookup)
		GPIO_LOOKUP_IDX(chip, sck, "sck", 0, GPIO_ACTIVE_HIGH);
	lookup->table[1] = (struct gpiod_lookup)
		GPIO_LOOKUP_IDX(chip, mosi, "mosi", 0, GPIO_ACTIVE_HIGH);
	/*
	 * spi-gpio drives the chip select with its logical value (SPI_CS_HIGH
	 * clear: active = 0), so a plain active-high lookup makes the line go
	 * low during a transfer, as on real hardware.
	 */
	lookup->table[2] = (struct gpiod_lookup)
		GPIO_LOOKUP_IDX(chip, cs, "cs", 0, GPIO_ACTIVE_HIGH);
	gpiod_add_lookup_table(lookup);

	pdev = platform_device_register_data(NULL, "spi_gpio", bus,
					     &pdata, sizeof(pdata));
	if (IS_ERR(pdev)) {
		ret = PTR_ERR(pdev);
		pdev = NULL;
		pr_err("ppm_spi_board: cannot add platform device spi_gpio.%d: %d\n",
		       bus, ret);
		goto err_table;
	}

	snprintf(name, sizeof(name), "spi%d", bus);
	dev = device_find_child(&pdev->dev, name, match_name);
	if (!dev) {
		pr_err("ppm_spi_board: spi_gpio.%d has no controller %s: is spi-gpio.ko loaded, does chip '%s' exist with lines %u, %u, %u? (see dmesg)\n",
		       bus, name, chip, sck, mosi, cs);
		ret = -ENODEV;
		goto err_pdev;
	}
	ctlr = container_of(dev, struct spi_controller, dev);
	spi = spi_new_device(ctlr, &info);
	put_device(dev);
	if (!spi) {
		pr_err("ppm_spi_board: cannot add SPI device %s.0\n", name);
		ret = -ENODEV;
		goto err_pdev;
	}
	pr_info("ppm_spi_board: %s on %s: sck %s:%u, mosi %s:%u, cs %s:%u (active low); bind spidev to %s\n",
		dev_name(&spi->dev), dev_name(&pdev->dev), chip, sck, chip,
		mosi, chip, cs, dev_name(&spi->dev));
	return 0;

err_pdev:
	platform_device_unregister(pdev);
	pdev = NULL;
err_table:
	gpiod_remove_lookup_table(lookup);
	kfree(lookup->dev_id);
err_lookup:
	kfree(lookup);
	lookup = NULL;
	return ret;
}

static void __exit ppm_spi_board_exit(void)
{
	spi_unregister_device(spi);
	platform_device_unregister(pdev);
	gpiod_remove_lookup_table(lookup);
	kfree(lookup->dev_id);
	kfree(lookup);
}

module_init(ppm_spi_board_init);
module_exit(ppm_spi_board_exit);

MODULE_LICENSE("GPL");
MODULE_DESCRIPTION("Board code for ppm's VM test: spi-gpio on gpio-sim lines, one spidev-bindable device");
